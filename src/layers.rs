//! The two kinds of layer the networks are made of, loaded and packed once.

use crate::plan::Planes;
use crate::pool::{Exec, Parts};
use crate::weights::{read_batch_norm, Init, TensorSource};
use crate::Result;
use alloc::format;
use alloc::vec::Vec;
use drivesim_kernels::pack;
use drivesim_kernels::{Activation, ConvParams, ConvShape, Matrix, OutputParts, Tensor, Winograd, OC_ALIGN};

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
            return exec.run(&|| {
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
        exec.run(&|| {
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
        exec.run(&|| {
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
    exec.run(&|| {
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

/// Below this many weights a dense layer is not worth sharing between threads: the pool's
/// hand-off costs about a microsecond, the product of a 256 x 256 matrix not much more.
const PARALLEL_MIN_WEIGHTS: usize = 1 << 16;

/// `y = act(W x + b)` with `W` `rows x cols`, packed in the kernels' panels ([`Matrix`]).
pub(crate) struct DenseLayer {
    weights: Tensor,
    pub bias: Vec<f32>,
    pub rows: usize,
    pub cols: usize,
    act: Activation,
}

impl DenseLayer {
    /// A layer from row-major weights, which it packs.
    pub fn new(weights: Tensor, bias: Vec<f32>, rows: usize, cols: usize, act: Activation) -> Self {
        let pack = |w: &[_]| pack::dense_weights(w, rows, cols);
        let weights = weights.map(pack, |w| pack::dense_weights(w, rows, cols));
        DenseLayer {
            weights,
            bias,
            rows,
            cols,
            act,
        }
    }

    pub fn matrix(&self) -> Matrix<'_> {
        Matrix {
            data: self.weights.as_data(),
            rows: self.rows,
            cols: self.cols,
        }
    }

    /// `y = act(W x + b)` for a batch (see [`dense`]).
    pub fn run(&self, exec: Exec<'_>, x: &[f32], y: &mut [f32]) {
        dense(exec, self.matrix(), &self.bias, self.act, x, y);
    }

    /// `y = act(y + W x)` for a batch: the bias left out, the sums added to what `y` holds
    /// (the bits of [`DenseLayer::run`] with that as the bias).
    pub fn run_add(&self, exec: Exec<'_>, x: &[f32], y: &mut [f32]) {
        let (isa, w, act) = (exec.isa, self.matrix(), self.act);
        match rows_shared(exec, w) {
            None => drivesim_kernels::dense_add(isa, w, act, x, y),
            Some(threads) => {
                let parts = OutputParts::new(y, w.rows, threads);
                exec.run(&|| {
                    while let Some(part) = parts.take() {
                        drivesim_kernels::dense_add_rows(isa, w, act, x, part);
                    }
                });
            }
        }
    }

    /// The packed weights as f32 ([`Matrix`]'s panels).
    #[cfg(feature = "train")]
    pub fn copy_packed(&self, packed: &mut [f32]) {
        match self.matrix().data {
            drivesim_kernels::MatrixData::F32(w) => packed.copy_from_slice(w),
            drivesim_kernels::MatrixData::F16(w) => packed.iter_mut().zip(w).for_each(|(d, w)| *d = w.to_f32()),
        }
    }

    /// Weight `(row, col)` as f32.
    #[cfg(feature = "train")]
    pub fn weight(&self, row: usize, col: usize) -> f32 {
        let at = Matrix::packed_index(row, col, self.cols);
        match self.matrix().data {
            drivesim_kernels::MatrixData::F32(w) => w[at],
            drivesim_kernels::MatrixData::F16(w) => w[at].to_f32(),
        }
    }
}

/// `y = act(W x + b)` for a batch; with threads, each takes a share of the rows (and so reads
/// only its share of the weights) for every item.
pub(crate) fn dense(exec: Exec<'_>, w: Matrix<'_>, bias: &[f32], act: Activation, x: &[f32], y: &mut [f32]) {
    let isa = exec.isa;
    let Some(threads) = rows_shared(exec, w) else {
        return drivesim_kernels::dense(isa, w, bias, act, x, y);
    };
    let parts = OutputParts::new(y, w.rows, threads);
    exec.run(&|| {
        while let Some(part) = parts.take() {
            drivesim_kernels::dense_rows(isa, w, bias, act, x, part);
        }
    });
}

/// The threads that share the rows of a product by `w`, or `None` where one thread does it.
fn rows_shared(exec: Exec<'_>, w: Matrix<'_>) -> Option<usize> {
    let threads = dense_parts(exec.threads(), w.rows, w.cols);
    (threads > 1).then_some(threads)
}

/// The parts [`dense`] cuts a `rows x cols` product's rows into for `threads` threads.
pub(crate) fn dense_parts(threads: usize, rows: usize, cols: usize) -> usize {
    match rows * cols >= PARALLEL_MIN_WEIGHTS {
        true => threads.max(1),
        false => 1,
    }
}
