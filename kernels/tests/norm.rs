//! BatchNorm in training mode and the per-channel sums against their definitions in f64: the
//! forward pass's statistics and outputs, and the backward pass against central differences of
//! an f64 forward pass (PyTorch parity is drivesim's `tests/train_layers.rs`).

mod common;

use common::{levels, Rng, ACTS};
use drivesim_kernels::norm::{
    batch_norm_backward, batch_norm_train, gradient_moments, moments, normalize, normalize_gradient, sums_len,
    update_running_stats,
};
use drivesim_kernels::{Activation, Isa, Plane};

/// Odd channel counts around the block of 16, small planes with and without a border.
const PLANES: [(usize, usize, usize, usize); 4] = [(2, 3, 1, 0), (3, 2, 5, 1), (2, 2, 17, 2), (1, 3, 33, 1)];
const ITEMS: usize = 3;

fn batch(rng: &mut Rng, plane: Plane, items: usize, scale: f32) -> Vec<f32> {
    let mut b = vec![0.0; plane.len() * items];
    for item in b.chunks_exact_mut(plane.len()) {
        let values: Vec<f32> = rng.fill(plane.interior_len(), scale).iter().map(|v| v + 0.5).collect();
        plane.write_interior(item, &values);
    }
    b
}

/// Offsets of every interior value of every item.
fn interior(plane: Plane, items: usize) -> Vec<(usize, usize)> {
    let mut at = Vec::new();
    for n in 0..items {
        for y in 0..plane.height {
            for x in 0..plane.width {
                for c in 0..plane.channels {
                    at.push((n * plane.len() + plane.index(y, x) + c, c));
                }
            }
        }
    }
    at
}

/// The layer in f64 from its definition: `Σ w · act(gamma · (x - mean) / sqrt(var + eps) + beta)`.
fn loss_f64(plane: Plane, x: &[f64], gamma: &[f64], beta: &[f64], act: Activation, w: &[f32]) -> f64 {
    let at = interior(plane, ITEMS);
    let count = (at.len() / plane.channels) as f64;
    let mut mean = vec![0.0; plane.channels];
    let mut var = vec![0.0; plane.channels];
    at.iter().for_each(|&(i, c)| mean[c] += x[i] / count);
    at.iter().for_each(|&(i, c)| var[c] += (x[i] - mean[c]).powi(2) / count);
    let apply = |v: f64| match act {
        Activation::Identity => v,
        Activation::Relu => v.max(0.0),
        Activation::LeakyRelu(s) => v.max(s as f64 * v),
        Activation::Tanh => v.tanh(),
    };
    at.iter()
        .map(|&(i, c)| w[i] as f64 * apply(gamma[c] * (x[i] - mean[c]) / (var[c] + 1e-5).sqrt() + beta[c]))
        .sum()
}

/// `batch_norm_train`'s output and statistics.
fn forward(
    isa: Isa,
    plane: Plane,
    x: &[f32],
    gamma: &[f32],
    beta: &[f32],
    act: Activation,
) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let c = plane.channels;
    let (mut y, mut mean, mut var) = (vec![0.0; x.len()], vec![0.0; c], vec![0.0; c]);
    let mut sums = vec![0.0; sums_len(c)];
    batch_norm_train(isa, plane, x, gamma, beta, act, &mut y, &mut mean, &mut var, &mut sums);
    (y, mean, var)
}

/// The passes that run on an instruction set give the scalar reference's results bit for bit,
/// on channel counts around every vector width and past a block of 64, adding to sums that
/// already hold values, and leave the border alone.
#[test]
fn every_level_sums_and_normalises_as_the_scalar_reference() {
    let mut rng = Rng::new(23);
    for (h, w, c, halo) in [
        (2, 3, 1, 0),
        (3, 2, 5, 1),
        (2, 2, 17, 2),
        (1, 3, 33, 1),
        (2, 1, 70, 1),
        (1, 2, 131, 0),
    ] {
        let plane = Plane::new(h, w, c, halo);
        let x = batch(&mut rng, plane, 1, 2.0);
        let g = rng.fill(plane.len(), 1.0);
        let mean = rng.fill(c, 1.0);
        let var: Vec<f32> = rng.fill(c, 1.0).iter().map(|v| v.abs() + 0.1).collect();
        let (gamma, beta) = (rng.fill(c, 1.5), rng.fill(c, 1.0));
        let start: Vec<f64> = rng.fill(sums_len(c), 3.0).iter().map(|&v| v as f64).collect();
        let run = |isa: Isa, g: &mut [f32]| {
            let (mut a, mut b) = (start.clone(), start.clone());
            moments(isa, plane, &x, &mut a);
            gradient_moments(isa, plane, &x, g, &mean, &mut b);
            normalize_gradient(isa, plane, &x, g, &mean, &var, &gamma, &b, 7);
            (a, b)
        };
        let want_g = {
            let mut g = g.clone();
            let sums = run(Isa::SCALAR, &mut g);
            (sums, g)
        };
        for isa in levels() {
            let mut got_g = g.clone();
            let sums = run(isa, &mut got_g);
            let bits = |v: &[f64]| v.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
            let name = isa.level().name();
            assert_eq!(bits(&sums.0), bits(&want_g.0 .0), "{name} {plane:?}: moments");
            assert_eq!(bits(&sums.1), bits(&want_g.0 .1), "{name} {plane:?}: gradient moments");
            let bits32 = |v: &[f32]| v.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
            assert_eq!(
                bits32(&got_g),
                bits32(&want_g.1),
                "{name} {plane:?}: normalised gradient"
            );
            // The border kept its values (random, not zero).
            let mut border = vec![true; plane.len()];
            interior(plane, 1).iter().for_each(|&(i, _)| border[i] = false);
            assert!(
                (0..plane.len()).all(|i| !border[i] || got_g[i] == g[i]),
                "{name} {plane:?}: border written"
            );
            // The forward normalisation, every activation (the SIMD ones follow the scalar
            // ones bit for bit), into an output whose border holds values it must keep.
            for act in ACTS {
                let (mut want_y, mut got_y) = (g.clone(), g.clone());
                normalize(Isa::SCALAR, plane, &x, &mean, &var, &gamma, &beta, act, &mut want_y);
                normalize(isa, plane, &x, &mean, &var, &gamma, &beta, act, &mut got_y);
                assert_eq!(bits32(&got_y), bits32(&want_y), "{name} {plane:?} {act:?}: normalised");
                assert!(
                    (0..plane.len()).all(|i| !border[i] || got_y[i] == g[i]),
                    "{name} {plane:?}: border"
                );
            }
        }
    }
}

#[test]
fn forward_matches_its_definition() {
    let mut rng = Rng::new(21);
    for (h, w, c, halo) in PLANES {
        let plane = Plane::new(h, w, c, halo);
        for (act, isa) in ACTS.into_iter().zip(levels().into_iter().cycle()) {
            let x = batch(&mut rng, plane, ITEMS, 2.0);
            let (gamma, beta) = (rng.fill(c, 1.5), rng.fill(c, 1.0));
            let (y, mean, var) = forward(isa, plane, &x, &gamma, &beta, act);
            let at = interior(plane, ITEMS);
            let count = (at.len() / c) as f64;
            for ch in 0..c {
                let values: Vec<f64> = at.iter().filter(|a| a.1 == ch).map(|&(i, _)| x[i] as f64).collect();
                let m = values.iter().sum::<f64>() / count;
                let v = values.iter().map(|x| (x - m).powi(2)).sum::<f64>() / count;
                assert!((mean[ch] as f64 - m).abs() <= 1e-6 * m.abs().max(1.0), "mean {ch}");
                assert!((var[ch] as f64 - v).abs() <= 1e-6 * v, "var {ch}");
            }
            for &(i, ch) in &at {
                let pre = gamma[ch] as f64 * (x[i] as f64 - mean[ch] as f64) / (var[ch] as f64 + 1e-5).sqrt()
                    + beta[ch] as f64;
                let want = act.apply(pre as f32);
                assert!(
                    (y[i] - want).abs() <= 1e-5 * (1.0 + want.abs()),
                    "{act:?} y {i}: {} vs {want}",
                    y[i]
                );
            }
            let border: f32 = y.iter().map(|v| v.abs()).sum::<f32>() - at.iter().map(|&(i, _)| y[i].abs()).sum::<f32>();
            assert_eq!(border, 0.0, "border written");
        }
    }
}

#[test]
fn backward_matches_central_differences() {
    let mut rng = Rng::new(22);
    for (h, w, c, halo) in PLANES {
        let plane = Plane::new(h, w, c, halo);
        for act in ACTS {
            let x = batch(&mut rng, plane, ITEMS, 2.0);
            let (gamma, beta) = (rng.fill(c, 1.5), rng.fill(c, 1.0));
            // The loss Σ w·y: its gradient with respect to y is w.
            let weights = rng.fill(x.len(), 1.0);
            let (y, mean, var) = forward(Isa::best(), plane, &x, &gamma, &beta, act);
            let mut dy = weights.clone();
            let mut dx = vec![0.0; x.len()];
            let (mut dgamma, mut dbeta) = (vec![0.0; c], vec![0.0; c]);
            batch_norm_backward(
                Isa::best(),
                plane,
                &x,
                &y,
                act,
                &gamma,
                &mean,
                &var,
                &mut dy,
                &mut dx,
                &mut dgamma,
                &mut dbeta,
                &mut vec![0.0; sums_len(c)],
            );
            let f64s = |v: &[f32]| v.iter().map(|&v| v as f64).collect::<Vec<f64>>();
            let (x64, g64, b64) = (f64s(&x), f64s(&gamma), f64s(&beta));
            let loss = |x: &[f64], g: &[f64], b: &[f64]| loss_f64(plane, x, g, b, act, &weights);
            let step = 1e-6;
            let central = |f: &dyn Fn(f64) -> f64| (f(step) - f(-step)) / (2.0 * step);
            let close = |got: f32, want: f64, what: &str| {
                assert!(
                    (got as f64 - want).abs() <= 1e-4 * (1.0 + want.abs()),
                    "{plane:?} {act:?} {what}: {got} vs {want}"
                )
            };
            for &(i, _) in interior(plane, ITEMS).iter().step_by(7) {
                let nudged = |d: f64| {
                    let mut x = x64.clone();
                    x[i] += d;
                    loss(&x, &g64, &b64)
                };
                close(dx[i], central(&nudged), &format!("dx {i}"));
            }
            for ch in 0..c {
                let nudged_gamma = |d: f64| {
                    let mut g = g64.clone();
                    g[ch] += d;
                    loss(&x64, &g, &b64)
                };
                let nudged_beta = |d: f64| {
                    let mut b = b64.clone();
                    b[ch] += d;
                    loss(&x64, &g64, &b)
                };
                close(dgamma[ch], central(&nudged_gamma), &format!("dgamma {ch}"));
                close(dbeta[ch], central(&nudged_beta), &format!("dbeta {ch}"));
            }
            // The gradient before the activation is what the layer below the BatchNorm's conv
            // bias sums: dbeta is its channel sum.
            let mut sums = vec![0.0; sums_len(c)];
            for g in dy.chunks_exact(plane.len()) {
                moments(Isa::best(), plane, g, &mut sums);
            }
            for ch in 0..c {
                assert!((sums[ch] as f32 - dbeta[ch]).abs() <= 1e-5 * (1.0 + dbeta[ch].abs()));
            }
        }
    }
}

#[test]
fn running_statistics_follow_pytorch() {
    // running = 0.9 · running + 0.1 · batch, the variance unbiased over 4 values.
    let (mut rm, mut rv) = (vec![1.0, -2.0], vec![0.5, 3.0]);
    update_running_stats(&[3.0, 0.0], &[0.75, 1.5], 4, &mut rm, &mut rv);
    assert_eq!(rm, [0.9 + 0.3, -1.8]);
    assert_eq!(rv, [0.45 + 0.1, 2.7 + 0.2]);
}
