//! A stack of convolutions: its saved activations and their gradients, its forward and backward
//! passes (weight gradients included), and the moves between planes and a dense layer's vectors.

use super::budget::{mul, Budget};
use super::layers::{Conv, Work};
use super::norm::{add, batch_sums, norm_backward, norm_forward};
use super::weight_grad::conv_weight_grad;
use crate::pool::{Exec, Parts};
use crate::Result;
use alloc::vec::Vec;
use core::ops::Range;
use drivesim_kernels::norm::moments;
use drivesim_kernels::{activation_backward, Activation, ConvKind, Plane};

/// The activations of a stack of convolutions for a batch, saved for the backward pass, and
/// the BatchNorm statistics of each of its passes (batches normalised on their own).
pub(super) struct Stack {
    /// Each layer's convolution output before BatchNorm (empty for layers without one).
    pub(super) z: Vec<Vec<f32>>,
    /// Each layer's output.
    pub(super) y: Vec<Vec<f32>>,
    /// Per layer, each pass's batch means and variances, `[pass][channel]`.
    mean: Vec<Vec<f32>>,
    var: Vec<Vec<f32>>,
}

/// The gradients of a stack's activations, one buffer per layer: of the layer's output, then in
/// place of its convolution's output (before BatchNorm and the activation).
pub(super) struct StackGrads {
    pub(super) g: Vec<Vec<f32>>,
}

pub(super) const PASSES: usize = 2;

pub(super) fn stack(budget: &mut Budget, layers: &[Conv], items: usize, what: &'static str) -> Result<Stack> {
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

pub(super) fn stack_grads(budget: &mut Budget, layers: &[Conv], items: usize) -> Result<StackGrads> {
    let mut g = Vec::new();
    for l in layers {
        let len = mul(items, l.shape.output.len())?;
        g.push(budget.take("activation gradients", len)?);
    }
    Ok(StackGrads { g })
}

/// Copies the interiors of `items` planes into consecutive HWC vectors (a dense layer's input).
pub(super) fn gather(plane: Plane, planes: &[f32], items: usize, flat: &mut [f32]) {
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
pub(super) fn scatter(plane: Plane, flat: &[f32], items: usize, planes: &mut [f32]) {
    let row = plane.width * plane.channels;
    let per_item = plane.height * row;
    for n in 0..items {
        for y in 0..plane.height {
            let dst = &mut planes[n * plane.len() + plane.index(y, 0)..][..row];
            dst.copy_from_slice(&flat[n * per_item + y * row..][..row]);
        }
    }
}

/// The forward pass of a stack of convolutions over the items of `passes` (each pass a batch
/// for BatchNorm, moving the running statistics if its flag says so).
#[allow(clippy::too_many_arguments)]
pub(super) fn stack_forward(
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

/// Where a backward pass through a stack starts: from the gradient of layer `i`'s output (in
/// `g[i]`), or of its convolution's output before BatchNorm and the activation (in `g[i]` too).
#[derive(Clone, Copy)]
pub(super) enum Start {
    Output(usize),
    BeforeNorm(usize),
}

/// The backward pass of a stack over the items of `passes` (with their BatchNorm statistics)
/// from `start` down: parameter gradients added to `grads` if given, `inject` (a layer and a
/// gradient) added to that layer's gradient before BatchNorm, and the input's gradient written
/// to `dx` if given.
#[allow(clippy::too_many_arguments)]
pub(super) fn stack_backward(
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
            let terms = match l.shape.kind {
                ConvKind::Down => (x, &*gz),
                ConvKind::Up => (&*gz, x),
            };
            let (scratch, partials) = (&mut work.weight_scratch[..], &mut work.partials[..]);
            let grad = &mut grads[l.weight.clone()];
            conv_weight_grad(exec, l.grad_shape(), terms, scratch, partials, grad);
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
