//! After a step's backward passes: the gradients checked, Adam on each network, and its
//! packings rebuilt; the passes over every parameter cut into pieces for the threads.

use super::layers::{Dense, Packed};
use super::networks::Networks;
use crate::error::{all_finite, expect_finite_output};
use crate::pool::{spans, Exec, Parts, SPANS};
use crate::train::adam::Adam;
use crate::Result;
use core::ops::Range;

/// One packing of [`Networks::pack`].
enum Job<'a> {
    Dense(&'a mut Dense),
    Conv(&'a mut Packed, Range<usize>),
}

/// Sets `data` to zero, threads taking pieces.
pub(super) fn zero(exec: Exec<'_>, data: &mut [f32]) {
    let spans = spans(data.len());
    let parts = Parts::spans(data, &spans);
    exec.run(&|| {
        while let Some((_, piece)) = parts.take() {
            piece.fill(0.0);
        }
    });
}

/// [`expect_finite_output`] on gradients, threads checking pieces (the index of the first bad
/// value is then searched alone).
fn expect_finite_gradients(exec: Exec<'_>, buffer: &'static str, data: &[f32]) -> Result<()> {
    let spans = spans(data.len());
    let mut finite = [true; SPANS];
    let flags = Parts::chunks(&mut finite[..], 1);
    exec.run(&|| {
        while let Some((i, flag)) = flags.take() {
            flag[0] = all_finite(&data[spans[i].clone()]);
        }
    });
    match finite.iter().all(|&f| f) {
        true => Ok(()),
        false => expect_finite_output(buffer, data),
    }
}

impl Networks {
    /// Repacks network `net`'s layers (0 encoder, 1 generator, 2 discriminator), threads
    /// taking the packings one at a time, the largest first.
    pub(super) fn pack(&mut self, net: usize, exec: Exec<'_>) {
        let p = &self.params;
        let (convs, dense) = match net {
            0 => (&mut self.enc, &mut self.heads),
            1 => (&mut self.gen, &mut self.fc),
            _ => (&mut self.dis, &mut self.logit),
        };
        let [a, b, c, d] = convs;
        let mut jobs = [
            Job::Dense(dense),
            Job::Conv(&mut d.backward, d.weight.clone()),
            Job::Conv(&mut d.forward, d.weight.clone()),
            Job::Conv(&mut c.backward, c.weight.clone()),
            Job::Conv(&mut c.forward, c.weight.clone()),
            Job::Conv(&mut b.backward, b.weight.clone()),
            Job::Conv(&mut b.forward, b.weight.clone()),
            Job::Conv(&mut a.backward, a.weight.clone()),
            Job::Conv(&mut a.forward, a.weight.clone()),
        ];
        let jobs = Parts::chunks(&mut jobs, 1);
        exec.run(&|| {
            while let Some((_, job)) = jobs.take() {
                match &mut job[0] {
                    Job::Dense(layer) => layer.pack(p),
                    Job::Conv(packed, weight) => packed.pack(exec.isa, &p[weight.clone()]),
                }
            }
        });
    }

    /// Adam on network `net`'s parameters, then its packings.
    pub(super) fn update(&mut self, net: usize, exec: Exec<'_>, adam: &Adam, t: u32, lr: f32) {
        let r = self.nets[net].clone();
        let [m, v] = &mut self.moments;
        let (params, grads) = (&mut self.params[r.clone()], &self.grads[r.clone()]);
        adam.update_shared(exec, (t, lr, 1.0), params, grads, [&mut m[r.clone()], &mut v[r]]);
        self.pack(net, exec);
    }

    /// Checks the gradients `range` before their update; if they are not finite, the running
    /// statistics go back to [`Networks::saved_stats`].
    pub(super) fn check_gradients(&mut self, exec: Exec<'_>, buffer: &'static str, range: Range<usize>) -> Result<()> {
        let checked = expect_finite_gradients(exec, buffer, &self.grads[range]);
        if checked.is_err() {
            self.stats.copy_from_slice(&self.saved_stats);
        }
        checked
    }
}
