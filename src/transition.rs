//! The transition model: `h' = tanh(W h + V z + U c + b)`, `z' = A h' + a`.

use crate::layers::DenseLayer;
use crate::plan::{zeros, Plan};
use crate::pool::{Exec, ItemParts};
use crate::sampling::Sampling;
use crate::texture::{Texture, TextureScratch};
use crate::weights::{Init, TensorSource};
use crate::{Config, Result};
use alloc::vec::Vec;
use core::ops::Range;
use drivesim_kernels::{Activation, Isa, Tensor};

/// The transition's layers, packed at load. A step sums the state's part first,
/// `[W | V] [h | z] + b`, then adds the action's, `U c`, and takes the tanh: candidates that
/// share a state share the first part, and each still gets the bits a step of its own would.
pub(crate) struct Transition {
    /// `[W | V]` and `b`: the state's part of a step from any code.
    input: DenseLayer,
    /// `W + V A` and `b + V a`: the state's part of a step from the code `h` itself predicted
    /// (`V z = V A h + V a`), half the weights to read. Only for f32 weights: for f16 ones it
    /// would have to be f32 to stay the weights' own product, and then it reads as many bytes
    /// as `[W | V]`.
    fed_back: Option<DenseLayer>,
    /// `U`: the action's part, added to the state's, then the tanh.
    action: DenseLayer,
    /// `A` and `a`.
    output: DenseLayer,
    /// `S` and `s`, where the model has them: the log standard deviation of each dimension of
    /// the next code, `S h' + s` (sampled futures, `crate::sampling`).
    spread: Option<DenseLayer>,
    /// `L`, where the model has it: the lower-triangular Cholesky factor of the correlation of
    /// the spread's noise across dimensions (the noise drawn is `L ε`, `ε` standard normal).
    noise_factor: Option<DenseLayer>,
    /// The texture net, where the model has it: sampled codes are drawn through it and not
    /// through the spread ([`crate::texture`]).
    texture: Option<Texture>,
}

/// Per-simulator scratch of the transition, as planned.
pub(crate) struct TransitionBuffers {
    /// Each batch element's input, `[h | z]` or `h`; when sampling through the texture net,
    /// its input `[temperature * ε | h']`.
    concat: Vec<f32>,
    /// The code `A h + a` that a fed-back step of an unfolded (f16) model recomputes; when
    /// sampling, the log standard deviation of each item's code, or the texture net's hidden
    /// layer (`max(z_dim, hidden_dim)` floats per item).
    code: Vec<f32>,
    /// When sampling: the standard normal noise of each item's code, then its correlated image
    /// (or the texture net's offsets).
    noise: Vec<f32>,
}

impl TransitionBuffers {
    pub fn new(plan: &Plan) -> Result<Self> {
        Ok(TransitionBuffers {
            concat: zeros(plan.transition_concat, plan.bytes())?,
            code: zeros(plan.transition_code, plan.bytes())?,
            noise: zeros(plan.sampling_noise, plan.bytes())?,
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
        let noise_factor = match src.contains(NOISE_FACTOR) {
            // The factor correlates the spread's noise: it means nothing without the spread.
            true if spread.is_none() => {
                return Err(crate::Error::MissingTensor {
                    name: SPREAD_WEIGHT.into(),
                })
            }
            true => Some(DenseLayer::new(
                src.tensor(NOISE_FACTOR, &[z, z], Init::FanIn(z))?,
                alloc::vec![0.0; z],
                z,
                z,
                Activation::Identity,
            )),
            false => None,
        };
        let (input, fed_back) = match (w, v) {
            // Both in f16: keep f16, the kernel widens it.
            (Tensor::F16(w), Tensor::F16(v)) => (Tensor::F16(concat_cols(&[(&w, hd), (&v, z)])), None),
            (w, v) => {
                let (w, v) = (w.into_f32(), v.into_f32());
                let (folded, bias) = fold_feedback(&w, &v, &b, &big_a.clone().into_f32(), &small_a, z);
                let fed_back = DenseLayer::new(Tensor::F32(folded), bias, hd, hd, Activation::Identity);
                (Tensor::F32(concat_cols(&[(&w, hd), (&v, z)])), Some(fed_back))
            }
        };
        Ok(Transition {
            input: DenseLayer::new(input, b, hd, hd + z, Activation::Identity),
            fed_back,
            action: DenseLayer::new(u, alloc::vec![0.0; hd], hd, a, Activation::Tanh),
            output: DenseLayer::new(big_a, small_a, z, hd, Activation::Identity),
            spread,
            noise_factor,
            texture: Texture::load(config, src)?,
        })
    }

    /// Whether the model can sample its codes: the spread head (`transition.S` and
    /// `transition.s`) or the texture net (`transition.texture.*`).
    pub fn samples(&self) -> bool {
        self.spread.is_some() || self.texture.is_some()
    }

    /// Samples through `texture` from now on (a sampler file's: [`crate::Model::from_bytes_with_sampler`]).
    pub(crate) fn set_texture(&mut self, texture: Texture) {
        self.texture = Some(texture);
    }

    /// The texture net's width, where the model has one.
    pub fn texture_width(&self) -> Option<usize> {
        self.texture.as_ref().map(Texture::width)
    }

    /// Whether the model correlates its sampled noise across dimensions (`transition.L`).
    pub fn correlates(&self) -> bool {
        self.noise_factor.is_some()
    }

    /// Turns the mean codes `codes` that a step predicted from the hidden states `h` it left
    /// into the samples of rollout step `step`: `code += temperature * exp(S h + s) * (L ε)`,
    /// `ε` drawn by `sampling` (without `L`: `ε` itself); with the texture net,
    /// `code += T([temperature * ε | h])` instead. Nothing changes for a model without either.
    /// The products run on the dense kernel, bit-identical for any threads.
    pub fn sample(
        &self,
        exec: Exec<'_>,
        buf: &mut TransitionBuffers,
        sampling: &Sampling,
        h: &[f32],
        step: u64,
        codes: &mut [f32],
    ) {
        if let Some(texture) = &self.texture {
            let half = buf.noise.len() / 2;
            let scratch = TextureScratch {
                input: &mut buf.concat,
                hidden: &mut buf.code,
                offsets: &mut buf.noise[half..],
            };
            return texture.sample(exec, sampling, h, step, codes, scratch);
        }
        let Some(spread) = &self.spread else {
            return;
        };
        let n = codes.len();
        let log_sigma = &mut buf.code[..n];
        spread.run(exec, h, log_sigma);
        let half = buf.noise.len() / 2;
        let (noise, correlated) = buf.noise.split_at_mut(half);
        let (noise, correlated) = (&mut noise[..n], &mut correlated[..n]);
        sampling.draw(noise, spread.rows, step);
        let noise = match &self.noise_factor {
            Some(factor) => {
                factor.run(exec, noise, correlated);
                &*correlated
            }
            None => &*noise,
        };
        sampling.add_spread(codes, log_sigma, noise);
    }

    /// The step's weights as a trainer holds them (its start): `[W | V | U]` packed
    /// ([`drivesim_kernels::Matrix`]) with `b`, and `A` packed with `a`.
    #[cfg(feature = "train")]
    pub fn trainer_weights(&self, input: (&mut [f32], &mut [f32]), output: (&mut [f32], &mut [f32])) {
        let (state, action) = (&self.input, &self.action);
        let cols = state.cols + action.cols;
        drivesim_kernels::pack::dense_from_fn(state.rows, cols, input.0, |r, c| match c.checked_sub(state.cols) {
            None => state.weight(r, c),
            Some(c) => action.weight(r, c),
        });
        input.1.copy_from_slice(&state.bias);
        self.output.copy_packed(output.0);
        output.1.copy_from_slice(&self.output.bias);
    }

    /// The spread head `S` with `s`, where the model has one (a trainer's start, the noise's fit).
    #[cfg(feature = "train")]
    pub fn spread_layer(&self) -> Option<&DenseLayer> {
        self.spread.as_ref()
    }

    /// Whether steps fed their own prediction run on `[W + V A | U]` (f32 weights).
    pub fn folds(&self) -> bool {
        self.fed_back.is_some()
    }

    /// One step for a batch, `h' = tanh(([W | V] [h | z] + b) + U c)` then `z' = A h' + a`,
    /// from the codes `z`, or, with `z` `None`, from the codes `h` itself predicts (`A h + a`,
    /// as in a rollout): then from `W + V A` where the model folds, else from `A h + a`
    /// computed here. The caller chooses: the result depends on the arguments alone. With
    /// threads and enough items, each thread steps a share of the items alone; with fewer,
    /// the threads share each product's rows ([`DenseLayer::run`]).
    pub fn step(
        &self,
        exec: Exec<'_>,
        buf: &mut TransitionBuffers,
        h: &mut [f32],
        z: Option<&[f32]>,
        action: &[f32],
        z_next: &mut [f32],
    ) {
        let (hd, zd) = (self.input.rows, self.output.rows);
        let batch = h.len() / hd;
        let ad = action.len().checked_div(batch).unwrap_or(0);
        let concat = &mut buf.concat[..batch * self.input.cols];
        let code = &mut buf.code[..batch * zd];
        by_items(
            exec,
            batch,
            [h, concat, code, z_next],
            |exec, items, [h, concat, code, z_next]| {
                let z = z.map(|z| &z[items.start * zd..items.end * zd]);
                let action = &action[items.start * ad..items.end * ad];
                let (input, z) = self.state_input(exec, h, z, code);
                let concat = &mut concat[..h.len() / hd * input.cols];
                gather(concat, hd, h, z);
                input.run(exec, concat, h);
                self.finish(exec, action, h, z_next);
            },
        );
    }

    /// [`Transition::step`] for a batch whose items all start from one hidden state `state`
    /// and one code `z` (or the code `state` predicts), each with its own action: the state's
    /// part is summed once, for one item, and every item still gets the bits of
    /// [`Transition::step`] (a planner's candidates, [`crate::Simulator::rollout_candidates`]).
    #[allow(clippy::too_many_arguments)]
    pub fn step_shared(
        &self,
        exec: Exec<'_>,
        buf: &mut TransitionBuffers,
        state: &[f32],
        z: Option<&[f32]>,
        action: &[f32],
        h: &mut [f32],
        z_next: &mut [f32],
    ) {
        let hd = self.input.rows;
        let (input, z) = self.state_input(exec, state, z, &mut buf.code[..self.output.rows]);
        let concat = &mut buf.concat[..input.cols];
        gather(concat, hd, state, z);
        let (first, rest) = h.split_at_mut(hd);
        input.run(exec, concat, first);
        for other in rest.chunks_exact_mut(hd) {
            other.copy_from_slice(first);
        }
        let ad = action.len().checked_div(h.len() / hd).unwrap_or(0);
        by_items(exec, h.len() / hd, [h, z_next], |exec, items, [h, z_next]| {
            self.finish(exec, &action[items.start * ad..items.end * ad], h, z_next);
        });
    }

    /// The layer of a step's state part from hidden states `h` and its code input: `[W | V]`
    /// with the codes `z`, or without them `W + V A` where the model folds, else `[W | V]` with
    /// the codes `A h + a`, computed into `code`.
    fn state_input<'a>(
        &'a self,
        exec: Exec<'_>,
        h: &[f32],
        z: Option<&'a [f32]>,
        code: &'a mut [f32],
    ) -> (&'a DenseLayer, Option<&'a [f32]>) {
        match (&self.fed_back, z) {
            (_, Some(z)) => (&self.input, Some(z)),
            (Some(fed_back), None) => (fed_back, None),
            (None, None) => {
                self.output.run(exec, h, code);
                (&self.input, Some(&*code))
            }
        }
    }

    /// A step's end from the state's part in `h`: `h = tanh(h + U c)`, `z' = A h + a`.
    fn finish(&self, exec: Exec<'_>, action: &[f32], h: &mut [f32], z_next: &mut [f32]) {
        self.action.run_add(exec, action, h);
        self.output.run(exec, h, z_next);
    }
}

/// Runs `step` on a batch of `items`: where there are enough of them, each thread runs it alone
/// on a share of the items (every layer, no barrier between them: a batch's items are
/// independent, and each gets the bits it would get alone); else once on all of them, with the
/// threads sharing each product's rows. `step` gets the items' range and their parts of
/// `buffers`, which hold whole items.
fn by_items<const B: usize>(
    exec: Exec<'_>,
    items: usize,
    buffers: [&mut [f32]; B],
    step: impl Fn(Exec<'_>, Range<usize>, [&mut [f32]; B]) + Sync,
) {
    let threads = exec.threads();
    if threads == 1 || items < ITEMS_PER_THREAD * threads {
        return step(exec, 0..items, buffers);
    }
    let parts = ItemParts::new(buffers, items, threads);
    let alone = Exec {
        isa: exec.isa,
        pool: None,
    };
    exec.run(&|| {
        while let Some((range, buffers)) = parts.take() {
            step(alone, range, buffers);
        }
    });
}

/// Below this many items per thread, threads share each product's rows instead of the items:
/// a thread with fewer items streams all the weights for little work.
const ITEMS_PER_THREAD: usize = 8;

/// The spread head's tensors: `S` `[z_dim, hidden_dim]` and `s` `[z_dim]` (optional).
pub(crate) const SPREAD_WEIGHT: &str = "transition.S";
pub(crate) const SPREAD_BIAS: &str = "transition.s";
/// The noise's correlation factor `L` `[z_dim, z_dim]` (optional; only with the spread head).
pub(crate) const NOISE_FACTOR: &str = "transition.L";

/// Writes each batch item's `[h | z]` (or `h` without `z`) to `concat`, the input of the step's
/// first product.
fn gather(concat: &mut [f32], hidden: usize, h: &[f32], z: Option<&[f32]>) {
    let batch = h.len() / hidden;
    let zd = z.map_or(0, |z| z.len() / batch);
    for (n, row) in concat.chunks_exact_mut(hidden + zd).enumerate() {
        row[..hidden].copy_from_slice(&h[n * hidden..][..hidden]);
        if let Some(z) = z {
            row[hidden..].copy_from_slice(&z[n * zd..][..zd]);
        }
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
