//! The transition's forward pass over windows of codes (every activation saved) and
//! back-propagation through time, with the products of the backward pass.

use super::settings::Backward;
use super::spread::{spread_loss, Saved};
use super::threads::{column_sums, each_row, product, weight_grad};
use super::trainer::TransitionTrainer;
use crate::pool::{spans, Exec, Parts, SPANS};
use crate::train::arena::{cut, cut_ref};
use crate::{Error, Result};
use drivesim_kernels::pack::dense_from_fn;
use drivesim_kernels::{Activation, Matrix, MatrixData};

impl TransitionTrainer<'_> {
    /// Runs the windows forward, saving every input, hidden state and prediction (time-major:
    /// item `t * batch + n`), and returns the loss.
    pub(super) fn forward(&mut self, codes: &[f32], actions: &[f32], batch: usize) -> Result<f32> {
        let (d, teacher) = (self.plan.dims, self.settings.teacher);
        let exec = Exec {
            isa: self.isa,
            pool: self.pool.as_ref(),
        };
        let [params, _, _, _, _, _, xs, hs, outs, _, dout, .., norm, _] = cut(self.memory.floats(), &self.plan.lens);
        let [wx, bx, wa, ba, ws, bs] = cut_ref(params, &d.params());
        let (h, z, a, cols) = (d.hidden, d.z, d.actions, d.cols());
        let (mean, std) = norm.split_at(a);
        let input = Matrix {
            data: MatrixData::F32(wx),
            rows: h,
            cols,
        };
        let output = Matrix {
            data: MatrixData::F32(wa),
            rows: z,
            cols: h,
        };
        let mut sum = 0.0f64;
        for t in 0..d.steps() {
            let (x, hs_t) = (&mut xs[t * batch * cols..][..batch * cols], t * batch * h);
            let (hs_read, outs_read) = (&*hs, &*outs);
            each_row(exec, x, cols, &|n, row| {
                let (h_prev, rest) = row.split_at_mut(h);
                let (z_in, c) = rest.split_at_mut(z);
                match t {
                    0 => h_prev.fill(0.0),
                    _ => h_prev.copy_from_slice(&hs_read[hs_t - batch * h + n * h..][..h]),
                }
                match t < teacher {
                    true => z_in.copy_from_slice(&codes[(n * d.window + t) * z..][..z]),
                    false => z_in.copy_from_slice(&outs_read[((t - 1) * batch + n) * z..][..z]),
                }
                let raw = &actions[(n * d.steps() + t) * a..][..a];
                for (((c, raw), m), s) in c.iter_mut().zip(raw).zip(mean).zip(std.iter()) {
                    *c = (raw - m) / s;
                }
            });
            let h_t = &mut hs[hs_t..][..batch * h];
            product(exec, input, bx, Activation::Tanh, x, h_t);
            let out = &mut outs[t * batch * z..][..batch * z];
            product(exec, output, ba, Activation::Identity, h_t, out);
            sum += squared_errors(exec, (d.window, t), z, out, codes);
        }
        let mut loss = sum / (batch * d.steps() * z) as f64;
        if d.spread {
            // The prediction gradients' buffer is free until the backward pass.
            let saved = Saved { hs, outs, codes, batch };
            loss += spread_loss(exec, d, teacher, (ws, bs), saved, dout, false);
        }
        let loss = loss as f32;
        if !loss.is_finite() {
            return Err(Error::NonFiniteOutput {
                buffer: "loss",
                index: 0,
            });
        }
        Ok(loss)
    }

    /// Back-propagation through time from the loss of the last [`forward`], newest step first:
    /// the gradients of every weight, or (`Backward::Inputs`) of every input instead.
    ///
    /// [`forward`]: TransitionTrainer::forward
    pub(super) fn backward(&mut self, codes: &[f32], batch: usize, what: Backward) -> Result<()> {
        let (d, teacher, full) = (self.plan.dims, self.settings.teacher, self.settings.full_bptt);
        let exec = Exec {
            isa: self.isa,
            pool: self.pool.as_ref(),
        };
        let [params, grads, _, _, bt, vut, xs, hs, outs, dpre, dout, dzc, gathered, zero, _, partials] =
            cut(self.memory.floats(), &self.plan.lens);
        let (h, z, a, cols, steps) = (d.hidden, d.z, d.actions, d.cols(), d.steps());
        if !self.transposed {
            let [wx, _, wa, ..] = cut_ref(params, &d.params());
            let wx_at = |r: usize, c: usize| wx[Matrix::packed_index(r, c, cols)];
            // [Aᵀ | Wᵀ]: the hidden state's gradient from the prediction's and the next step's.
            dense_from_fn(h, z + h, bt, |r, c| match c < z {
                true => wa[Matrix::packed_index(c, r, h)],
                false => wx_at(c - z, r),
            });
            // [Vᵀ ; Uᵀ]: the gradient of the code and action inputs.
            dense_from_fn(z + a, h, vut, |r, c| wx_at(c, h + r));
            self.transposed = true;
        }
        let matrix = |w, rows, cols| Matrix {
            data: MatrixData::F32(w),
            rows,
            cols,
        };
        let (bt, vut) = (matrix(bt, h, z + h), matrix(vut, z + a, h));
        // d loss / d prediction: 2 (prediction - code) / (values in the loss).
        let scale = 2.0 / (batch * steps * z) as f32;
        let outs_read = &*outs;
        each_row(exec, &mut dout[..steps * batch * z], z, &|item, g| {
            let (t, n) = (item / batch, item % batch);
            let target = &codes[(n * d.window + t + 1) * z..][..z];
            for ((g, o), y) in g.iter_mut().zip(&outs_read[item * z..][..z]).zip(target) {
                *g = scale * (o - y);
            }
        });
        let inputs = what == Backward::Inputs || full;
        for t in (0..steps).rev() {
            let later = t + 1 < steps;
            let dout_t = &mut dout[t * batch * z..][..batch * z];
            if full && later && t + 1 >= teacher {
                // The next step's input was this prediction: its gradient joins the loss's.
                let dz_next = &dzc[(t + 1) * batch * (z + a)..][..batch * (z + a)];
                for (g, dz) in dout_t.chunks_exact_mut(z).zip(dz_next.chunks_exact(z + a)) {
                    g.iter_mut().zip(dz).for_each(|(g, dz)| *g += dz);
                }
            }
            let g = &mut gathered[..batch * (z + h)];
            let (dout_t, dpre_read) = (&*dout_t, &*dpre);
            each_row(exec, g, z + h, &|n, row| {
                row[..z].copy_from_slice(&dout_t[n * z..][..z]);
                match later {
                    true => row[z..].copy_from_slice(&dpre_read[((t + 1) * batch + n) * h..][..h]),
                    false => row[z..].fill(0.0),
                }
            });
            step_backward(
                exec,
                bt,
                &zero[..h],
                g,
                &hs[t * batch * h..][..batch * h],
                &mut dpre[t * batch * h..][..batch * h],
            );
            if inputs {
                let dpre_t = &dpre[t * batch * h..][..batch * h];
                product(
                    exec,
                    vut,
                    &zero[..z + a],
                    Activation::Identity,
                    dpre_t,
                    &mut dzc[t * batch * (z + a)..][..batch * (z + a)],
                );
            }
        }
        if what == Backward::Weights {
            let [gwx, gbx, gwa, gba, gws, gbs] = cut(grads, &d.params());
            let items = steps * batch;
            weight_grad(exec, (&dpre[..items * h], &xs[..items * cols]), h, cols, partials, gwx);
            column_sums(exec, &dpre[..items * h], gbx);
            weight_grad(exec, (&dout[..items * z], &hs[..items * h]), z, h, partials, gwa);
            column_sums(exec, &dout[..items * z], gba);
            if d.spread {
                // The input gradients' buffer is free once the steps are done.
                let [.., ws, bs] = cut_ref(params, &d.params());
                let saved = Saved { hs, outs, codes, batch };
                // The head's loss covers the teacher-forced steps, the first items.
                let forced = teacher.min(steps) * batch;
                let dls = &mut dzc[..forced * z];
                spread_loss(exec, d, teacher, (ws, bs), saved, dls, true);
                weight_grad(exec, (dls, &hs[..forced * h]), z, h, partials, gws);
                column_sums(exec, dls, gbs);
            }
        }
        Ok(())
    }
}

/// One step of the RNN backward: `dh = [Aᵀ | Wᵀ] [dz' | dpre_next]` (the hidden state feeds
/// the prediction and the next step), then through the tanh: `dpre = dh (1 - h²)`.
fn step_backward(exec: Exec<'_>, bt: Matrix<'_>, zero: &[f32], gathered: &[f32], h: &[f32], dpre: &mut [f32]) {
    product(exec, bt, zero, Activation::Identity, gathered, dpre);
    let len = bt.rows;
    each_row(exec, dpre, len, &|n, row| {
        drivesim_kernels::activation_backward(exec.isa, Activation::Tanh, &h[n * len..][..len], row)
    });
}

/// The sum of squared errors of step `t`'s predictions `out` (`batch` windows) against their
/// codes, in f64: threads sum fixed spans of the windows, the spans are added in order.
fn squared_errors(exec: Exec<'_>, (window, t): (usize, usize), z: usize, out: &[f32], codes: &[f32]) -> f64 {
    let spans = spans(out.len() / z);
    let mut sums = [0.0f64; SPANS];
    let slots = Parts::chunks(&mut sums[..], 1);
    exec.run(&|| {
        while let Some((i, slot)) = slots.take() {
            for n in spans[i].clone() {
                let target = &codes[(n * window + t + 1) * z..][..z];
                let diff = |(o, y): (&f32, &f32)| ((o - y) as f64) * ((o - y) as f64);
                slot[0] += out[n * z..][..z].iter().zip(target).map(diff).sum::<f64>();
            }
        }
    });
    sums.iter().sum()
}
