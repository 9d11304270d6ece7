//! The correlation of the sampled noise across the code's dimensions (`transition.L`,
//! [`crate::sampling`]): fitted once a transition with a spread head is trained, from its
//! one-step errors on the training drives, scaled by the spread it predicted for them.
//! `weights/drivesim_reference/sequences.py`'s `noise_factor` fits the same, step for step.

use crate::plan::Plan;
use crate::pool::Exec;
use crate::sampling::sigma;
use crate::transition::TransitionBuffers;
use crate::{Error, Model, Result};
use alloc::format;
use alloc::string::ToString;
use alloc::vec;
use alloc::vec::Vec;
use drivesim_kernels::Isa;

/// The lower-triangular Cholesky factor `L` (`[z_dim, z_dim]`, row-major) of the correlation
/// of `model`'s standardised one-step errors on `drives`, for `transition.L`.
///
/// Each drive is its codes (`[T, z_dim]`) and the actions between them (`[T - 1, action_dim]`,
/// or `[T, action_dim]` whose last is unused). Along each drive the transition is stepped from
/// a zero state on the true codes (teacher-forced); each prediction's error, divided by the
/// spread the head predicts for it (`(z - mean) / exp(S h' + s)`), is one sample. Their
/// covariance (population, in f64) scaled to unit diagonal is the correlation; a dimension
/// without variance is uncorrelated. Sampling with `L` keeps each dimension's spread the
/// head's and draws the dimensions together as the errors moved.
///
/// Errors: [`Error::NoSampling`] for a model without the spread head; [`Error::BufferLength`]
/// or [`Error::NonFinite`] for a malformed drive; [`Error::Episodes`] when the drives hold no
/// more steps than the code has dimensions, or the correlation is singular.
pub fn fit_noise_factor(model: &Model, drives: &[(&[f32], &[f32])]) -> Result<Vec<f32>> {
    let c = model.config();
    let (z, hd, a) = (c.z_dim, c.hidden_dim, c.action_dim);
    let Some(spread) = model.transition.spread_layer() else {
        return Err(Error::NoSampling);
    };
    let plan = Plan::new(c, 1, 1)?;
    let mut buffers = TransitionBuffers::new(&plan)?;
    let exec = Exec {
        isa: Isa::best(),
        pool: None,
    };
    let (mut h, mut mean, mut log_sigma, mut error) =
        (vec![0.0f32; hd], vec![0.0f32; z], vec![0.0f32; z], vec![0.0f64; z]);
    let (mut sums, mut products, mut steps) = (vec![0.0f64; z], vec![0.0f64; z * z], 0usize);
    for &(codes, actions) in drives {
        check_drive(codes, actions, z, a)?;
        h.fill(0.0);
        for t in 0..codes.len() / z - 1 {
            let action = &actions[t * a..][..a];
            model.transition.step(
                exec,
                &mut buffers,
                &mut h,
                Some(&codes[t * z..][..z]),
                action,
                &mut mean,
            );
            spread.run(exec, &h, &mut log_sigma);
            let truth = &codes[(t + 1) * z..][..z];
            for (((e, &y), &m), &l) in error.iter_mut().zip(truth).zip(&mean).zip(&log_sigma) {
                *e = ((y - m) / sigma(l)) as f64;
            }
            for (i, &ei) in error.iter().enumerate() {
                sums[i] += ei;
                let row = &mut products[i * z..][..=i];
                row.iter_mut().zip(&error).for_each(|(p, &ej)| *p += ei * ej);
            }
            steps += 1;
        }
    }
    if steps <= z {
        return Err(Error::Episodes {
            reason: format!("the noise's correlation needs more one-step errors than the code's {z} dimensions: the drives hold {steps}"),
        });
    }
    let correlation = correlation(&sums, &products, steps as f64);
    cholesky(&correlation, z).ok_or_else(|| Error::Episodes {
        reason: "the one-step errors' correlation is singular (dimensions that move together exactly)".to_string(),
    })
}

/// `factor` (a `transition.L`: `[z_dim, z_dim]` row-major, lower-triangular, e.g.
/// [`fit_noise_factor`]'s) sharpened: the Cholesky factor of its correlation `L Lᵀ` raised to
/// `power` and scaled back to unit diagonal, so that each dimension's spread stays the head's
/// and the noise gathers in the directions the one-step errors share most (power 1 gives the
/// factor back as it is). `weights/drivesim_reference/sequences.py`'s `sharpen_noise` computes the same.
///
/// The trade-off it moves along, measured on held-out drivers (docs/history/next_second.md): at power
/// 2 the best of 16 sampled futures at 30 steps comes nearer what happened (0.94-0.97 of the
/// mean code's error, from 1.01-1.02) and the sampled codes' norm falls (0.89-0.90 of the real
/// codes', from 0.91-0.92).
///
/// Errors: [`Error::Config`] for power 0; [`Error::BufferLength`] for a factor that is not
/// square; [`Error::NonFinite`] for one that is not finite; [`Error::Episodes`] where the
/// sharpened correlation is singular.
pub fn sharpen_noise_factor(factor: &[f32], power: u32) -> Result<Vec<f32>> {
    if power == 0 {
        return Err(Error::Config {
            field: "noise factor's power",
            expected: "at least 1",
            found: 0,
        });
    }
    let z = factor.len().isqrt();
    if z == 0 || z * z != factor.len() {
        return Err(Error::BufferLength {
            buffer: "factor",
            expected: z * z,
            found: factor.len(),
        });
    }
    crate::error::expect_finite("factor", factor)?;
    if power == 1 {
        return Ok(factor.to_vec());
    }
    let l: Vec<f64> = factor.iter().map(|&v| v as f64).collect();
    let c = times_transposed(&l, &l, z);
    // C is symmetric: P C = P Cᵀ.
    let p = (1..power).fold(c.clone(), |p, _| times_transposed(&p, &c, z));
    let r = unit_diagonal(z, |i, j| p[i * z + j]);
    cholesky(&r, z).ok_or_else(|| Error::Episodes {
        reason: format!("the noise's correlation to the power {power} is singular"),
    })
}

/// `a bᵀ` of two row-major `[z, z]` matrices, in f64.
fn times_transposed(a: &[f64], b: &[f64], z: usize) -> Vec<f64> {
    let mut out = vec![0.0; z * z];
    for (i, row) in out.chunks_exact_mut(z).enumerate() {
        for (j, value) in row.iter_mut().enumerate() {
            *value = a[i * z..][..z].iter().zip(&b[j * z..][..z]).map(|(x, y)| x * y).sum();
        }
    }
    out
}

/// A drive's codes whole items and finite, with `T - 1` or `T` actions.
fn check_drive(codes: &[f32], actions: &[f32], z: usize, a: usize) -> Result<()> {
    let frames = crate::error::whole_items("codes", codes, z)?;
    if !(actions.len() == frames * a || actions.len() + a == frames * a) || frames == 0 {
        return Err(Error::BufferLength {
            buffer: "actions",
            expected: frames.saturating_sub(1) * a,
            found: actions.len(),
        });
    }
    crate::error::expect_finite("codes", codes)?;
    crate::error::expect_finite("actions", actions)
}

/// The correlation (lower triangle, row-major `[z, z]`) of samples whose sums and sums of
/// products (lower triangle) over `n` samples are given.
fn correlation(sums: &[f64], products: &[f64], n: f64) -> Vec<f64> {
    let z = sums.len();
    let mean: Vec<f64> = sums.iter().map(|s| s / n).collect();
    unit_diagonal(z, |i, j| products[i * z + j] / n - mean[i] * mean[j])
}

/// The symmetric `[z, z]` matrix `m(i, j)` (read for `j <= i`) scaled to unit diagonal, its
/// lower triangle row-major: `m(i, j) / sqrt(m(i, i) m(j, j))`, 0 off the diagonal where a
/// dimension has no variance.
fn unit_diagonal(z: usize, m: impl Fn(usize, usize) -> f64) -> Vec<f64> {
    let std: Vec<f64> = (0..z).map(|i| drivesim_kernels::math::sqrt(m(i, i).max(0.0))).collect();
    let mut r = vec![0.0; z * z];
    for i in 0..z {
        for j in 0..=i {
            r[i * z + j] = match (i == j, std[i] * std[j] > 1e-12) {
                (true, _) => 1.0,
                (false, true) => m(i, j) / (std[i] * std[j]),
                (false, false) => 0.0,
            };
        }
    }
    r
}

/// The Cholesky factor of a symmetric matrix given by its lower triangle (row-major `[z, z]`),
/// in f32; `None` where it is not positive definite.
fn cholesky(m: &[f64], z: usize) -> Option<Vec<f32>> {
    let mut l = vec![0.0f64; z * z];
    for i in 0..z {
        for j in 0..=i {
            let dot: f64 = (0..j).map(|k| l[i * z + k] * l[j * z + k]).sum();
            let v = m[i * z + j] - dot;
            l[i * z + j] = if i == j {
                // NaN fails too.
                if v.partial_cmp(&1e-10) != Some(core::cmp::Ordering::Greater) {
                    return None;
                }
                drivesim_kernels::math::sqrt(v)
            } else {
                v / l[j * z + j]
            };
        }
    }
    Some(l.into_iter().map(|v| v as f32).collect())
}

/// `file` (a drivesim weight file whose transition has the spread head) with `factor` as its
/// `transition.L` (in the file's dtype), e.g. [`fit_noise_factor`]'s: sampled futures then
/// draw correlated noise ([`Model::samples_correlated`]).
#[cfg(feature = "std")]
pub fn with_noise_factor(file: &[u8], factor: &[f32]) -> Result<Vec<u8>> {
    let model = Model::from_bytes(file)?;
    let z = model.config().z_dim;
    if !model.samples() {
        return Err(Error::NoSampling);
    }
    crate::error::expect_len("factor", factor, z * z)?;
    crate::error::expect_finite("factor", factor)?;
    let tensor = (crate::transition::NOISE_FACTOR.to_string(), vec![z, z], factor.to_vec());
    super::shared::weight_file(file, &[tensor], None, None, super::TrainedOn::default())
}
