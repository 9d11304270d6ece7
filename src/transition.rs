//! The transition model: `h' = tanh(W h + V z + U c + b)`, `z' = A h' + a`.

use crate::layers::DenseLayer;
use crate::plan::{zeros, Plan};
use crate::pool::Exec;
use crate::weights::{Init, TensorSource};
use crate::{Config, Result};
use alloc::vec::Vec;
use drivesim_kernels::{Activation, Isa, Tensor};

pub(crate) struct Transition {
    /// `[W | V | U]` and `b`: a step from any code.
    input: DenseLayer,
    /// `[W + V A | U]` and `b + V a`: a step from the code `h` itself predicted (`V z = V A h + V a`),
    /// a third fewer weights to read. Only for f32 weights: for f16 ones it would have to be
    /// f32 to stay the weights' own product, and then it reads as many bytes as `[W | V]`.
    fed_back: Option<DenseLayer>,
    /// `A` and `a`.
    output: DenseLayer,
    /// `S` and `s`, where the model has them: the log standard deviation of each dimension of
    /// the next code, `S h' + s` (sampled futures, `crate::sampling`).
    spread: Option<DenseLayer>,
}

/// Per-simulator scratch of the transition, as planned.
pub(crate) struct TransitionBuffers {
    /// Each batch element's input, `[h | z | c]` or `[h | c]`.
    concat: Vec<f32>,
    /// The code `A h + a` that a fed-back step of an unfolded (f16) model recomputes.
    code: Vec<f32>,
}

impl TransitionBuffers {
    pub fn new(plan: &Plan) -> Result<Self> {
        Ok(TransitionBuffers {
            concat: zeros(plan.transition_concat, plan.bytes())?,
            code: zeros(plan.transition_code, plan.bytes())?,
        })
    }

    /// The gathered-input buffer, `hidden_dim + z_dim + action_dim` floats per item: also the
    /// policy's input `[z | h]`, which is shorter.
    pub fn concat(&mut self) -> &mut [f32] {
        &mut self.concat
    }
}

impl Transition {
    pub fn load(config: &Config, src: &mut dyn TensorSource) -> Result<Self> {
        let (hd, z, a) = (config.hidden_dim, config.z_dim, config.action_dim);
        let fan_in = Init::FanIn(hd + z + a);
        let w = src.tensor("transition.W", &[hd, hd], fan_in)?;
        let v = src.tensor("transition.V", &[hd, z], fan_in)?;
        let u = src.tensor("transition.U", &[hd, a], fan_in)?;
        let b = src.f32("transition.b", &[hd], fan_in)?;
        let big_a = src.tensor("transition.A", &[z, hd], Init::FanIn(hd))?;
        let small_a = src.f32("transition.a", &[z], Init::FanIn(hd))?;
        let spread = match src.contains(SPREAD_WEIGHT) || src.contains(SPREAD_BIAS) {
            true => Some(DenseLayer::new(
                src.tensor(SPREAD_WEIGHT, &[z, hd], Init::FanIn(hd))?,
                src.f32(SPREAD_BIAS, &[z], Init::FanIn(hd))?,
                z,
                hd,
                Activation::Identity,
            )),
            false => None,
        };
        let (input, fed_back) = match (w, v, u) {
            // All three in f16: keep f16, the kernel widens it.
            (Tensor::F16(w), Tensor::F16(v), Tensor::F16(u)) => {
                (Tensor::F16(concat_cols(&[(&w, hd), (&v, z), (&u, a)])), None)
            }
            (w, v, u) => {
                let (w, v, u) = (w.into_f32(), v.into_f32(), u.into_f32());
                let (folded, bias) = fold_feedback(&w, &v, &b, &big_a.clone().into_f32(), &small_a, z);
                let weights = Tensor::F32(concat_cols(&[(&folded, hd), (&u, a)]));
                let fed_back = DenseLayer::new(weights, bias, hd, hd + a, Activation::Tanh);
                let input = Tensor::F32(concat_cols(&[(&w, hd), (&v, z), (&u, a)]));
                (input, Some(fed_back))
            }
        };
        Ok(Transition {
            input: DenseLayer::new(input, b, hd, hd + z + a, Activation::Tanh),
            fed_back,
            output: DenseLayer::new(big_a, small_a, z, hd, Activation::Identity),
            spread,
        })
    }

    /// Whether the model predicts its codes' spread (`transition.S` and `transition.s`).
    pub fn samples(&self) -> bool {
        self.spread.is_some()
    }

    /// The log standard deviation `S h + s` of the next code of each hidden state `h` (after a
    /// step), into the buffers' scratch; `None` for a model without the spread head.
    pub fn log_sigma<'b>(&self, exec: Exec<'_>, buf: &'b mut TransitionBuffers, h: &[f32]) -> Option<&'b [f32]> {
        let spread = self.spread.as_ref()?;
        let out = &mut buf.code[..h.len() / spread.cols * spread.rows];
        spread.run(exec, h, out);
        Some(out)
    }

    /// The step's two layers: `[W | V | U]` with `b`, and `A` with `a` (a trainer's start).
    #[cfg(feature = "train")]
    pub fn layers(&self) -> (&DenseLayer, &DenseLayer) {
        (&self.input, &self.output)
    }

    /// The spread head `S` with `s`, where the model has one (a trainer's start).
    #[cfg(feature = "train")]
    pub fn spread_layer(&self) -> Option<&DenseLayer> {
        self.spread.as_ref()
    }

    /// Whether steps fed their own prediction run on `[W + V A | U]` (f32 weights).
    pub fn folds(&self) -> bool {
        self.fed_back.is_some()
    }

    /// One step for a batch, `h' = tanh([W | V | U] [h | z | c] + b)` then `z' = A h' + a`, from
    /// the codes `z`, or, with `z` `None`, from the codes `h` itself predicts (`A h + a`, as in
    /// a rollout): then from
    /// `[W + V A | U]` where the model folds, else from `A h + a` computed here. The caller
    /// chooses: the result depends on the arguments alone. With threads, each product is split
    /// between them by rows ([`DenseLayer::run`]), so the two products are two tasks, the
    /// second waiting for all of `h'`.
    pub fn step(
        &self,
        exec: Exec<'_>,
        buf: &mut TransitionBuffers,
        h: &mut [f32],
        z: Option<&[f32]>,
        action: &[f32],
        z_next: &mut [f32],
    ) {
        let (input, z) = match (&self.fed_back, z) {
            (_, Some(z)) => (&self.input, Some(z)),
            (Some(fed_back), None) => (fed_back, None),
            (None, None) => {
                let code = &mut buf.code[..h.len() / self.input.rows * self.output.rows];
                self.output.run(exec, h, code);
                (&self.input, Some(&*code))
            }
        };
        let concat = &mut buf.concat[..h.len() / input.rows * input.cols];
        gather(concat, input.rows, h, z, action);
        input.run(exec, concat, h);
        self.output.run(exec, h, z_next);
    }
}

/// The spread head's tensors: `S` `[z_dim, hidden_dim]` and `s` `[z_dim]` (optional).
pub(crate) const SPREAD_WEIGHT: &str = "transition.S";
pub(crate) const SPREAD_BIAS: &str = "transition.s";

/// Writes each batch item's `[h | z | c]` (or `[h | c]` without `z`) to `concat`, the input of
/// the step's first product.
fn gather(concat: &mut [f32], hidden: usize, h: &[f32], z: Option<&[f32]>, action: &[f32]) {
    let batch = h.len() / hidden;
    let (zd, ad) = (z.map_or(0, |z| z.len() / batch), action.len() / batch);
    for (n, row) in concat.chunks_exact_mut(hidden + zd + ad).enumerate() {
        row[..hidden].copy_from_slice(&h[n * hidden..][..hidden]);
        if let Some(z) = z {
            row[hidden..hidden + zd].copy_from_slice(&z[n * zd..][..zd]);
        }
        row[hidden + zd..].copy_from_slice(&action[n * ad..][..ad]);
    }
}

/// `W + V A` (row-major) and `b + V a`: the input weights of a step fed its own prediction.
/// Computed once, at load, with the dense kernel of this CPU (0.4 s at z = hidden = 2048, 8 ms
/// at 512).
fn fold_feedback(w: &[f32], v: &[f32], b: &[f32], big_a: &[f32], small_a: &[f32], z: usize) -> (Vec<f32>, Vec<f32>) {
    let hd = b.len();
    // `V` times `A` as the dense kernel's batch: the rows of `V` are the items and `A^T` the
    // matrix, so that the output is `V A` row-major.
    let a_t = DenseLayer::new(
        Tensor::F32(transpose(big_a, z, hd)),
        alloc::vec![0.0; hd],
        hd,
        z,
        Activation::Identity,
    );
    let mut folded = alloc::vec![0.0; hd * hd];
    a_t.run(
        Exec {
            isa: Isa::best(),
            pool: None,
        },
        v,
        &mut folded,
    );
    for (f, w) in folded.iter_mut().zip(w) {
        *f += w;
    }
    let bias = v
        .chunks_exact(z)
        .zip(b)
        .map(|(row, b)| b + row.iter().zip(small_a).map(|(v, a)| v * a).sum::<f32>())
        .collect();
    (folded, bias)
}

/// A row-major `rows x cols` matrix transposed, in square blocks that stay in cache.
fn transpose(m: &[f32], rows: usize, cols: usize) -> Vec<f32> {
    const BLOCK: usize = 32;
    let mut t = alloc::vec![0.0; m.len()];
    for r0 in (0..rows).step_by(BLOCK) {
        for c0 in (0..cols).step_by(BLOCK) {
            for r in r0..rows.min(r0 + BLOCK) {
                for c in c0..cols.min(c0 + BLOCK) {
                    t[c * rows + r] = m[r * cols + c];
                }
            }
        }
    }
    t
}

/// Places row-major matrices with the same row count side by side: `(values, cols)` each.
fn concat_cols<T: Copy>(parts: &[(&Vec<T>, usize)]) -> Vec<T> {
    let rows = parts.first().map_or(0, |(v, cols)| v.len() / cols.max(&1));
    let mut out = Vec::with_capacity(parts.iter().map(|(v, _)| v.len()).sum());
    for r in 0..rows {
        for (v, cols) in parts {
            out.extend_from_slice(&v[r * cols..][..*cols]);
        }
    }
    out
}
