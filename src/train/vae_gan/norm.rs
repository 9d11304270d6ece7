//! BatchNorm in training mode: the forward pass with batch statistics, the per-channel sums
//! (the same whatever the thread count), and the backward pass.

use super::layers::Work;
use super::table::Norm;
use crate::pool::{Exec, Parts};
use drivesim_kernels::norm::{
    gradient_moments, moments, normalize, normalize_gradient, parameter_gradients, statistics, sums_len,
    update_running_stats,
};
use drivesim_kernels::{activation_backward, Activation, Plane};

/// `dst += src`.
pub(super) fn add(dst: &mut [f32], src: &[f32]) {
    dst.iter_mut().zip(src).for_each(|(d, s)| *d += s);
}

/// BatchNorm + activation in training mode over one pass of `plane`s, moving the running
/// statistics if `update`.
#[allow(clippy::too_many_arguments)] // a layer's tensors, its input and output, its statistics
pub(super) fn norm_forward(
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
pub(super) fn batch_sums<'w>(
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
pub(super) fn norm_backward(
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
