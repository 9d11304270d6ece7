//! One VAE-GAN step, top to bottom as it runs: the forward passes (encoder, generator,
//! discriminator), the discriminator's loss, backward pass and update, then the encoder's and
//! generator's losses, their backward passes and their updates; after it, the discriminator's
//! and generator's passes the step calls.

use super::loss::bce;
use super::networks::Networks;
use super::norm::{norm_backward, norm_forward};
use super::stack::{gather, scatter, stack_backward, stack_forward, Start};
use super::trainer::{VaeGanLosses, VaeGanSettings};
use super::update::zero;
use crate::pool::Exec;
use crate::Result;
use core::ops::Range;
use drivesim_kernels::{math, Activation};

impl Networks {
    /// One VAE-GAN step on `n` frames; see [`VaeGanTrainer::step`](super::VaeGanTrainer::step).
    /// `t` is the Adam step.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn step(
        &mut self,
        exec: Exec<'_>,
        s: &VaeGanSettings,
        frames: &[f32],
        eps: &[f32],
        prior: &[f32],
        n: usize,
        lr: f32,
        t: u32,
    ) -> Result<VaeGanLosses> {
        zero(exec, &mut self.grads);
        self.saved_stats.copy_from_slice(&self.stats);
        let z = self.fc.cols;
        let image = self.enc[0].shape.input;
        {
            let b = &mut self.buffers;
            for (plane, frame) in b
                .real
                .chunks_exact_mut(image.len())
                .zip(frames.chunks_exact(image.interior_len()))
            {
                image.write_interior(plane, frame);
            }
            // Encoder.
            let passes = [(0..n, true)];
            stack_forward(
                exec,
                &self.enc,
                &self.params,
                &mut self.stats,
                &b.real,
                &mut b.enc,
                &passes,
                &mut b.work,
            );
            gather(self.enc[3].shape.output, &b.enc.y[3], n, &mut b.enc_flat);
            let flat = self.heads.cols;
            self.heads
                .run(exec, &self.params, &b.enc_flat[..n * flat], &mut b.heads[..n * 2 * z]);
            // The generator's inputs: mu + eps · exp(logsigma), then the prior samples.
            b.eps[..n * z].copy_from_slice(eps);
            for i in 0..n {
                let (mu, ls) = b.heads[i * 2 * z..][..2 * z].split_at_mut(z);
                for j in 0..z {
                    ls[j] = math::tanh(ls[j]);
                    b.codes[i * z + j] = mu[j] + eps[i * z + j] * math::exp64(ls[j] as f64) as f32;
                }
            }
            b.codes[n * z..2 * n * z].copy_from_slice(prior);
            // Generator: reconstructions update the running statistics, prior samples do not.
            self.fc.run(
                exec,
                &self.params,
                &b.codes[..2 * n * z],
                &mut b.fc_out[..2 * n * self.fc.rows],
            );
            scatter(self.top, &b.fc_out, 2 * n, &mut b.top_z);
            let (tl, tc) = (self.top.len(), self.top.channels);
            for (p, update) in [(0, true), (1, false)] {
                let span = p * n * tl..(p + 1) * n * tl;
                let statistics = (&mut b.top_mean[p * tc..][..tc], &mut b.top_var[p * tc..][..tc]);
                let (z, y) = (&b.top_z[span.clone()], &mut b.top_y[span]);
                let (norm, relu) = (&self.top_norm, Activation::Relu);
                norm_forward(
                    exec,
                    self.top,
                    norm,
                    &self.params,
                    &mut self.stats,
                    relu,
                    z,
                    y,
                    statistics,
                    update,
                    &mut b.work,
                );
            }
            let passes = [(0..n, true), (n..2 * n, false)];
            stack_forward(
                exec,
                &self.gen,
                &self.params,
                &mut self.stats,
                &b.top_y,
                &mut b.gen,
                &passes,
                &mut b.work,
            );
        }

        // The discriminator: real frames against reconstructions and prior samples.
        self.discriminate(exec, false, n);
        self.discriminate(exec, true, 2 * n);
        let b = &mut self.buffers;
        let real = bce(&b.logits_real[..n], true, 1.0, &mut b.dlogits[..n]);
        self.discriminator_backward(exec, false, n, true, false, false);
        let b = &mut self.buffers;
        let fake = bce(&b.logits_fake[..2 * n], false, 1.0, &mut b.dlogits[..2 * n]);
        self.discriminator_backward(exec, true, 2 * n, true, false, false);
        self.check_gradients(exec, "discriminator gradients", self.nets[2].clone())?;
        self.update(2, exec, &s.adam, t, lr);
        let d = self.dis_stats;
        self.saved_stats[d..].copy_from_slice(&self.stats[d..]);

        // The encoder's and generator's losses through the updated discriminator.
        self.discriminate(exec, false, n);
        self.discriminate(exec, true, 2 * n);
        let b = &mut self.buffers;
        let features = self.dis[2].shape.output;
        let (fl, f_len) = (features.len(), n * features.interior_len());
        let (f_real, f_fake) = (&b.dis_real.z[2][..n * fl], &b.dis_fake.z[2][..n * fl]);
        // Interior values only: the borders are zero in both.
        let (mut sum, mut sq, mut err) = (0.0f64, 0.0f64, 0.0f64);
        for (&r, &f) in f_real.iter().zip(f_fake) {
            sum += r as f64;
            err += ((f - r) as f64) * ((f - r) as f64);
        }
        let mean = sum / f_len as f64;
        for item in f_real.chunks_exact(fl) {
            for y in 0..features.height {
                for &r in &item[features.index(y, 0)..][..features.width * features.channels] {
                    sq += (r as f64 - mean) * (r as f64 - mean);
                }
            }
        }
        let spread = (sq / (f_len as f64 - 1.0)).max(1e-6);
        let feature = err / f_len as f64 / spread;
        let dfeature_scale = s.feature as f64 * 2.0 / (f_len as f64 * spread);
        b.dfeature.fill(0.0);
        for ((d, &r), &f) in b.dfeature.iter_mut().zip(f_real).zip(f_fake) {
            *d = (dfeature_scale * (f - r) as f64) as f32;
        }
        // Pixel L1 and its gradient (sign(0) = 0, as PyTorch's).
        let (il, pixels) = (image.len(), n * image.interior_len());
        let (xr, x) = (&b.gen.y[3][..n * il], &b.real[..n * il]);
        let pixel = xr.iter().zip(x).map(|(&r, &x)| (r - x).abs() as f64).sum::<f64>() / pixels as f64;
        let pixel_grad = |r: f32, x: f32| -> f32 {
            let d = r - x;
            let sign = if d > 0.0 {
                1.0
            } else if d < 0.0 {
                -1.0
            } else {
                0.0
            };
            (s.pixel as f64 * sign / pixels as f64) as f32
        };
        // KL prior.
        let codes = (n * z) as f64;
        let mut kl = 0.0;
        for item in b.heads[..n * 2 * z].chunks_exact(2 * z) {
            let (mu, ls) = item.split_at(z);
            for (&m, &l) in mu.iter().zip(ls) {
                let (m, l) = (m as f64, l as f64);
                kl += m * m + math::exp64(2.0 * l) - 1.0 - 2.0 * l;
            }
        }
        let kl = 0.5 * kl / codes;
        let gan = bce(&b.logits_fake[..2 * n], true, s.gan as f64, &mut b.dlogits[..2 * n]);

        // The encoder's loss: the feature error back through the discriminator (from its third
        // convolution down), plus the pixel error, back through the reconstructions' pass of
        // the generator to the codes, the reparametrisation and the KL prior.
        let fake_len = 2 * n * fl;
        b.dis_grads.g[2][..fake_len].copy_from_slice(&b.dfeature[..fake_len]);
        let passes = [0..2 * n];
        stack_backward(
            exec,
            &self.dis,
            &self.params,
            None,
            &b.gen.y[3],
            &b.dis_fake,
            &mut b.dis_grads,
            &passes,
            Start::BeforeNorm(2),
            None,
            Some(&mut b.dx),
            &mut b.work,
        );
        for ((d, &r), &x) in b.dx[..n * il].iter_mut().zip(xr).zip(x) {
            *d += pixel_grad(r, x);
        }
        self.generator_backward(exec, &[0..n], false);
        let b = &mut self.buffers;
        for i in 0..n {
            let (mu, ls) = b.heads[i * 2 * z..][..2 * z].split_at(z);
            let (dmu, dls) = b.dheads[i * 2 * z..][..2 * z].split_at_mut(z);
            for j in 0..z {
                let (m, l, dc, e) = (
                    mu[j] as f64,
                    ls[j] as f64,
                    b.dcodes[i * z + j] as f64,
                    b.eps[i * z + j] as f64,
                );
                let sigma = math::exp64(l);
                dmu[j] = (dc + s.kl as f64 * m / codes) as f32;
                let dl = dc * e * sigma + s.kl as f64 * (math::exp64(2.0 * l) - 1.0) / codes;
                dls[j] = (dl * (1.0 - l * l)) as f32;
            }
        }
        let flat = self.heads.cols;
        let dheads = &b.dheads[..n * 2 * z];
        self.heads
            .weight_grad(exec, dheads, &b.enc_flat[..n * flat], &mut self.grads);
        self.heads
            .data_grad(exec, &self.params, dheads, &mut b.dflat[..n * flat]);
        scatter(self.enc[3].shape.output, &b.dflat, n, &mut b.enc_grads.g[3]);
        let passes = [0..n];
        stack_backward(
            exec,
            &self.enc,
            &self.params,
            Some(&mut self.grads),
            &b.real,
            &b.enc,
            &mut b.enc_grads,
            &passes,
            Start::Output(3),
            None,
            None,
            &mut b.work,
        );

        // The generator's loss: the GAN term and the feature error back through the
        // discriminator to both fakes, plus the pixel error, back through both passes.
        self.discriminator_backward(exec, true, 2 * n, false, true, true);
        let b = &mut self.buffers;
        let (xr, x) = (&b.gen.y[3][..n * il], &b.real[..n * il]);
        for ((d, &r), &x) in b.dx[..n * il].iter_mut().zip(xr).zip(x) {
            *d += pixel_grad(r, x);
        }
        self.generator_backward(exec, &[0..n, n..2 * n], true);

        self.check_gradients(exec, "encoder and generator gradients", 0..self.nets[1].end)?;
        self.update(0, exec, &s.adam, t, lr);
        self.update(1, exec, &s.adam, t, lr);
        let recon = s.feature as f64 * feature + s.pixel as f64 * pixel;
        Ok(VaeGanLosses {
            discriminator: (real + fake) as f32,
            encoder: (s.kl as f64 * kl + recon) as f32,
            generator: (recon + s.gan as f64 * gan) as f32,
            gan: gan as f32,
            feature: feature as f32,
            pixel_l1: pixel as f32,
            kl: kl as f32,
        })
    }

    /// The discriminator on `items` planes of `input` (real frames, or the fakes in the
    /// generator's output): its activations in `set`, the logits in `logits`.
    fn discriminate(&mut self, exec: Exec<'_>, fake: bool, items: usize) {
        let b = &mut self.buffers;
        let (input, acts, flat, logits) = if fake {
            (&b.gen.y[3], &mut b.dis_fake, &mut b.flat_fake, &mut b.logits_fake)
        } else {
            (&b.real, &mut b.dis_real, &mut b.flat_real, &mut b.logits_real)
        };
        let passes = [(0..items, true)];
        stack_forward(
            exec,
            &self.dis,
            &self.params,
            &mut self.stats,
            input,
            acts,
            &passes,
            &mut b.work,
        );
        gather(self.dis[3].shape.output, &acts.y[3], items, flat);
        self.logit.run(
            exec,
            &self.params,
            &flat[..items * self.logit.cols],
            &mut logits[..items],
        );
    }

    /// The gradient `dlogits` (of `items` logits) back through the discriminator's `fake` or
    /// real set: to its parameters if `weights`, to its input (into `buffers.dx`) if `input`,
    /// with `inject` added to the third convolution's output gradient.
    fn discriminator_backward(
        &mut self,
        exec: Exec<'_>,
        fake: bool,
        items: usize,
        weights: bool,
        input: bool,
        inject: bool,
    ) {
        let b = &mut self.buffers;
        let (x, acts, flat) = if fake {
            (&b.gen.y[3], &b.dis_fake, &b.flat_fake)
        } else {
            (&b.real, &b.dis_real, &b.flat_real)
        };
        let flat_len = self.logit.cols;
        let dlogits = &b.dlogits[..items];
        if weights {
            self.logit
                .weight_grad(exec, dlogits, &flat[..items * flat_len], &mut self.grads);
        }
        self.logit
            .data_grad(exec, &self.params, dlogits, &mut b.dflat[..items * flat_len]);
        scatter(self.dis[3].shape.output, &b.dflat, items, &mut b.dis_grads.g[3]);
        let grads = weights.then_some(&mut self.grads[..]);
        let inject = inject.then_some((2, &b.dfeature[..]));
        let dx = input.then_some(&mut b.dx[..]);
        let passes = [0..items];
        stack_backward(
            exec,
            &self.dis,
            &self.params,
            grads,
            x,
            acts,
            &mut b.dis_grads,
            &passes,
            Start::Output(3),
            inject,
            dx,
            &mut b.work,
        );
    }

    /// The generator's gradient `buffers.dx` (of its `items` outputs) back through its first
    /// `items` (with their passes' statistics): parameter gradients if `weights`, the codes'
    /// gradient into `buffers.dcodes` otherwise.
    fn generator_backward(&mut self, exec: Exec<'_>, passes: &[Range<usize>], weights: bool) {
        let b = &mut self.buffers;
        let items = passes.last().map_or(0, |p| p.end);
        let image = self.gen[3].shape.output.len();
        b.gen_grads.g[3][..items * image].copy_from_slice(&b.dx[..items * image]);
        let grads = weights.then_some(&mut self.grads[..]);
        let (top_y, gen) = (&b.top_y, &b.gen);
        stack_backward(
            exec,
            &self.gen,
            &self.params,
            grads,
            top_y,
            gen,
            &mut b.gen_grads,
            passes,
            Start::Output(3),
            None,
            Some(&mut b.top_g),
            &mut b.work,
        );
        // BatchNorm0 + ReLU on the fully connected layer's output, per pass.
        let (top, tl, c) = (self.top, self.top.len(), self.top.channels);
        let norm = &self.top_norm;
        for (p, r) in passes.iter().enumerate() {
            let s = r.start * tl..r.end * tl;
            let statistics = (&b.top_mean[p * c..][..c], &b.top_var[p * c..][..c]);
            let saved = (&b.top_z[s.clone()], &b.top_y[s.clone()]);
            let grads = weights.then_some(&mut self.grads[..]);
            let (relu, g) = (Activation::Relu, &mut b.top_g[s]);
            norm_backward(
                exec,
                top,
                norm,
                &self.params,
                grads,
                relu,
                saved,
                statistics,
                g,
                &mut b.work,
            );
        }
        let flat = self.fc.rows;
        gather(top, &b.top_g, items, &mut b.dflat);
        let (dflat, z) = (&b.dflat[..items * flat], self.fc.cols);
        if weights {
            self.fc.weight_grad(exec, dflat, &b.codes[..items * z], &mut self.grads);
        } else {
            self.fc.data_grad(exec, &self.params, dflat, &mut b.dcodes[..items * z]);
        }
    }
}
