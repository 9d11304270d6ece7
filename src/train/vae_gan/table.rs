//! The three networks' tensors as the trainer lays them out: each tensor's name, PyTorch shape,
//! place in the parameters (or the running statistics) and initialisation.

use crate::weights::Init;
use alloc::format;
use alloc::string::String;
use alloc::vec::Vec;
use core::ops::Range;
use drivesim_kernels::pack::conv_matrix_len;
use drivesim_kernels::{ConvKind, ConvShape, Matrix};

/// One tensor of the three networks: its name, PyTorch shape, place (in the parameters, or in
/// the running statistics) and initialisation where the file has none.
pub(super) struct Entry {
    pub(super) name: String,
    pub(super) shape: Vec<usize>,
    pub(super) at: Range<usize>,
    pub(super) param: bool,
    pub(super) init: Init,
    pub(super) layout: Layout,
}

/// How a tensor is kept in the parameters.
#[derive(Clone, Copy)]
pub(super) enum Layout {
    /// As PyTorch's.
    Torch,
    /// A dense layer's weights, packed: the layer (see [`Networks::dense`](super::networks::Networks::dense)) and the tensor's
    /// first row in it; `at` is then the whole layer's packed matrix.
    Dense(usize, usize),
    /// A convolution's weights, in the layout of their gradient for this shape (see
    /// [`conv_weights_from_matrix`](drivesim_kernels::pack::conv_weights_from_matrix)).
    Conv(ConvShape),
}

/// The tensors, laid out as they are declared.
#[derive(Default)]
pub(super) struct Table {
    pub(super) entries: Vec<Entry>,
    pub(super) params: usize,
    pub(super) stats: usize,
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
    pub(super) fn conv(&mut self, name: String, shape: ConvShape, init: Init) -> Range<usize> {
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
    pub(super) fn packed(&mut self, layer: usize, tensors: &[(&str, usize)], cols: usize, init: Init) -> Range<usize> {
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

    pub(super) fn param(&mut self, name: String, shape: &[usize], init: Init) -> Range<usize> {
        self.add(name, shape, true, init)
    }

    /// A BatchNorm layer's four tensors.
    pub(super) fn norm(&mut self, name: &str, channels: usize) -> Norm {
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
pub(super) struct Norm {
    pub(super) gamma: Range<usize>,
    pub(super) beta: Range<usize>,
    pub(super) mean: Range<usize>,
    pub(super) var: Range<usize>,
}
