//! The two kinds of layer the networks are made of, loaded and packed once.

use crate::plan::{zeros, StackPlan};
use crate::pool::{Exec, Parts};
use crate::weights::{Init, Tensor, TensorSource};
use crate::{Error, Result};
use alloc::format;
use alloc::vec::Vec;
use drivesim_kernels::pack::{self, BatchNorm};
use drivesim_kernels::{f16, Activation, ConvParams, ConvShape, Matrix, MatrixData, OutputParts, Winograd, OC_ALIGN};

/// A convolution with its BatchNorm folded in and its activation fused, computed directly or,
/// where [`Winograd::new`] takes the layer, by Winograd's algorithm (with its weights packed
/// for that).
pub(crate) struct ConvLayer {
    pub shape: ConvShape,
    winograd: Option<Winograd>,
    weights: Vec<f32>,
    bias: Vec<f32>,
    act: Activation,
}

impl ConvLayer {
    /// Reads `{name}.weight` / `{name}.bias` (and `{bn}.*` when given) and packs them.
    pub fn load(
        src: &mut dyn TensorSource,
        name: &str,
        bn: Option<&str>,
        shape: ConvShape,
        act: Activation,
    ) -> Result<Self> {
        let (k, ic, oc) = (shape.kernel, shape.input.channels, shape.output.channels);
        let (torch_shape, fan_in) = match shape.kind {
            drivesim_kernels::ConvKind::Down => ([oc, ic, k, k], ic * k * k),
            drivesim_kernels::ConvKind::Up => ([ic, oc, k, k], oc * k * k),
        };
        let weight = src.f32(&format!("{name}.weight"), &torch_shape, Init::FanIn(fan_in))?;
        let bias = src.f32(&format!("{name}.bias"), &[oc], Init::FanIn(fan_in))?;
        let bn = bn.map(|bn| read_batch_norm(src, bn, oc)).transpose()?;
        let bn = bn.as_ref().map(|p| p.view());
        let winograd = Winograd::new(shape);
        let (weights, bias) = match &winograd {
            Some(w) => pack::winograd_weights(w, &weight, &bias, bn),
            None => pack::conv_weights(&shape, &weight, &bias, bn),
        };
        Ok(ConvLayer {
            shape,
            winograd,
            weights,
            bias,
            act,
        })
    }

    /// Runs the layer; with threads, a direct layer has each take blocks of output channels
    /// until none is left (and so read only the weights of its blocks). Taking blocks as they
    /// come, rather than a fixed share, keeps both busy when one core runs slower (a busy
    /// neighbour, a lower clock). A Winograd layer shares its input transform by stride
    /// phases, then gives each thread a share of the output channels.
    pub fn run(&self, exec: Exec<'_>, input: &[f32], output: &mut [f32], scratch: Scratch<'_>) {
        let (isa, threads, channels) = (exec.isa, exec.threads(), self.shape.output.channels);
        let layer = ConvParams {
            shape: self.shape,
            weights: &self.weights,
            bias: &self.bias,
            act: self.act,
        };
        let blocks = channels.div_ceil(BLOCK_CHANNELS);
        let single = threads == 1 || blocks < 2;
        let Some(w) = &self.winograd else {
            if single {
                return drivesim_kernels::conv(isa, layer, input, output);
            }
            let parts = OutputParts::new(output, channels, blocks);
            return exec.run(&|_| {
                while let Some(part) = parts.take() {
                    drivesim_kernels::conv_channels(isa, layer, input, part);
                }
            });
        };
        let v = &mut scratch.transformed[..w.input_len()];
        if single {
            let products = &mut scratch.products[..w.scratch_len()];
            return drivesim_kernels::winograd_conv(isa, w, layer, input, v, products, output);
        }
        let spans: [_; 4] = core::array::from_fn(|phase| w.phase_span(phase));
        let phases = Parts::spans(&mut *v, &spans);
        exec.run(&|_| {
            while let Some((phase, span)) = phases.take() {
                drivesim_kernels::winograd_input(isa, w, phase, input, span);
            }
        });
        let v = &*v;
        let products = Parts::chunks(scratch.products, w.scratch_len());
        // A share of whole panels per thread, in one call: the kernel then reads the larger of
        // weights and transformed input once per call (see `winograd_channels`), where blocks
        // taken one at a time would each read it again.
        let parts = OutputParts::new(output, channels, threads);
        exec.run(&|_| {
            let (_, scratch) = products.take().expect("product scratch for every thread");
            while let Some(part) = parts.take() {
                drivesim_kernels::winograd_channels(isa, w, layer, v, scratch, part);
            }
        });
    }
}

/// The Winograd layers' buffers that [`ConvLayer::run`] uses.
pub(crate) struct Scratch<'a> {
    transformed: &'a mut [f32],
    products: &'a mut [f32],
}

/// Output channels threads take at a time: two panels, the kernels' widest block of channels.
const BLOCK_CHANNELS: usize = 2 * OC_ALIGN;

/// The buffers of a chain of convolutions running one image at a time.
pub(crate) struct Planes {
    /// The padded input plane of each layer.
    inputs: Vec<Vec<f32>>,
    /// The transformed input of the largest Winograd layer.
    transformed: Vec<f32>,
    /// Winograd product scratch, one per thread that may share a layer on these planes.
    products: Vec<f32>,
}

impl Planes {
    /// The zeroed buffers of set `set` of `stack`.
    fn new(stack: &StackPlan, set: usize, plan_bytes: usize) -> Result<Self> {
        let products = if set == 0 {
            stack.products_first
        } else {
            stack.products_other
        };
        let mut inputs = Vec::with_capacity(stack.inputs.len());
        for &len in &stack.inputs {
            inputs.push(zeros(len, plan_bytes)?);
        }
        Ok(Planes {
            inputs,
            transformed: zeros(stack.transformed, plan_bytes)?,
            products: zeros(products, plan_bytes)?,
        })
    }

    /// The first layer's input plane.
    pub fn input(&mut self) -> &mut [f32] {
        &mut self.inputs[0]
    }
}

/// Per-simulator buffers of a convolution stack (the encoder's or the generator's), as planned.
pub(crate) struct StackBuffers {
    /// The padded input plane of every convolution: one set, or one per thread when threads
    /// take whole items of a batch.
    pub planes: Vec<Planes>,
    /// The flat features between the convolutions and the dense layer, for a whole batch.
    pub flat: Vec<f32>,
}

impl StackBuffers {
    pub fn new(stack: &StackPlan, flat: usize, plan_bytes: usize) -> Result<Self> {
        let mut planes = Vec::with_capacity(stack.sets);
        for set in 0..stack.sets {
            planes.push(Planes::new(stack, set, plan_bytes)?);
        }
        Ok(StackBuffers {
            planes,
            flat: zeros(flat, plan_bytes)?,
        })
    }
}

/// Runs `convs` in turn: the first input plane (already filled) through the others to `output`.
pub(crate) fn run_convs(exec: Exec<'_>, convs: &[ConvLayer], planes: &mut Planes, output: &mut [f32]) {
    for (i, conv) in convs.iter().enumerate() {
        let (done, rest) = planes.inputs.split_at_mut(i + 1);
        let output = rest.first_mut().map_or(&mut *output, |next| next.as_mut_slice());
        let scratch = Scratch {
            transformed: &mut planes.transformed,
            products: &mut planes.products,
        };
        conv.run(exec, &done[i], output, scratch);
    }
}

/// Calls `f(exec, planes, input, output)` for each item of a batch: `input` holds items of
/// `in_len` values, `output` items of `out_len`. With a set of planes per thread and at least
/// as many items as threads, each thread takes whole items on its own planes (no hand-off
/// between layers); otherwise the items go one by one and each layer shares the threads.
pub(crate) fn for_each_item(
    exec: Exec<'_>,
    planes: &mut [Planes],
    input: &[f32],
    in_len: usize,
    output: &mut [f32],
    out_len: usize,
    f: impl Fn(Exec<'_>, &mut Planes, &[f32], &mut [f32]) + Sync,
) {
    let (items, threads) = (input.len() / in_len, exec.threads());
    if threads == 1 || items < threads || planes.len() < threads {
        let planes = &mut planes[0];
        for (x, y) in input.chunks_exact(in_len).zip(output.chunks_exact_mut(out_len)) {
            f(exec, planes, x, y);
        }
        return;
    }
    // Each thread takes a set of planes, then items until none is left.
    let planes = Parts::chunks(planes, 1);
    let outputs = Parts::chunks(&mut output[..items * out_len], out_len);
    exec.run(&|_| {
        let alone = Exec {
            isa: exec.isa,
            pool: None,
        };
        let (_, planes) = planes.take().expect("a set of planes for every thread");
        while let Some((i, y)) = outputs.take() {
            f(alone, &mut planes[0], &input[i * in_len..][..in_len], y);
        }
    });
}

/// BatchNorm parameters as read from a source.
pub(crate) struct BatchNormParams([Vec<f32>; 4]);

impl BatchNormParams {
    pub fn view(&self) -> BatchNorm<'_> {
        let [weight, bias, running_mean, running_var] = &self.0;
        BatchNorm {
            weight,
            bias,
            running_mean,
            running_var,
        }
    }
}

/// Reads BatchNorm `name`'s four tensors; a negative running variance is an error.
pub(crate) fn read_batch_norm(src: &mut dyn TensorSource, name: &str, channels: usize) -> Result<BatchNormParams> {
    let mut read = |part: &str, init| src.f32(&format!("{name}.{part}"), &[channels], init);
    let params = [
        read("weight", Init::Ones)?,
        read("bias", Init::Zeros)?,
        read("running_mean", Init::Zeros)?,
        read("running_var", Init::Ones)?,
    ];
    if let Some(index) = params[3].iter().position(|&v| v < 0.0) {
        return Err(Error::BadWeight {
            name: format!("{name}.running_var"),
            index,
            value: params[3][index],
            expected: "a variance, at least 0",
        });
    }
    Ok(BatchNormParams(params))
}

/// Below this many weights a dense layer is not worth sharing between threads: the pool's
/// hand-off costs about a microsecond, the product of a 256 x 256 matrix not much more.
const PARALLEL_MIN_WEIGHTS: usize = 1 << 16;

/// Weights of a dense layer: row-major as loaded, packed by [`DenseLayer::new`].
pub(crate) enum DenseWeights {
    F32(Vec<f32>),
    F16(Vec<f16>),
}

impl From<Tensor> for DenseWeights {
    fn from(t: Tensor) -> Self {
        match t {
            Tensor::F32(v) => DenseWeights::F32(v),
            Tensor::F16(v) => DenseWeights::F16(v),
        }
    }
}

/// `y = act(W x + b)` with `W` `rows x cols`, packed in the kernels' panels ([`Matrix`]).
pub(crate) struct DenseLayer {
    weights: DenseWeights,
    pub bias: Vec<f32>,
    pub rows: usize,
    pub cols: usize,
    act: Activation,
}

impl DenseLayer {
    /// A layer from row-major weights, which it packs.
    pub fn new(weights: DenseWeights, bias: Vec<f32>, rows: usize, cols: usize, act: Activation) -> Self {
        let weights = match weights {
            DenseWeights::F32(w) => DenseWeights::F32(pack::dense_weights(&w, rows, cols)),
            DenseWeights::F16(w) => DenseWeights::F16(pack::dense_weights(&w, rows, cols)),
        };
        DenseLayer {
            weights,
            bias,
            rows,
            cols,
            act,
        }
    }

    pub fn matrix(&self) -> Matrix<'_> {
        let data = match &self.weights {
            DenseWeights::F32(w) => MatrixData::F32(w),
            DenseWeights::F16(w) => MatrixData::F16(w),
        };
        Matrix {
            data,
            rows: self.rows,
            cols: self.cols,
        }
    }

    /// `y = act(W x + b)` for a batch; with threads, each takes a share of the rows (and so
    /// reads only its share of the weights) for every item.
    pub fn run(&self, exec: Exec<'_>, x: &[f32], y: &mut [f32]) {
        let (isa, threads) = (exec.isa, exec.threads());
        if threads == 1 || self.rows * self.cols < PARALLEL_MIN_WEIGHTS {
            return drivesim_kernels::dense(isa, self.matrix(), &self.bias, self.act, x, y);
        }
        let parts = OutputParts::new(y, self.rows, threads);
        exec.run(&|_| {
            while let Some(part) = parts.take() {
                drivesim_kernels::dense_rows(isa, self.matrix(), &self.bias, self.act, x, part);
            }
        });
    }
}
