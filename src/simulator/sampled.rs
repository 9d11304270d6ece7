//! Sampled futures ([`crate::sampling`]): [`Simulator::set_sampling`] and
//! [`Simulator::sample`], which the rollouts call after each step.

use super::Simulator;
use crate::error::{expect_finite, expect_finite_output, expect_len};
use crate::pool::Exec;
use crate::sampling::Sampling;
use crate::transition::TransitionBuffers;
use crate::{Error, Model, Result};
use core::borrow::Borrow;

impl<M: Borrow<Model>> Simulator<M> {
    /// Samples the futures of every later rollout of this simulator ([`Simulator::rollout`],
    /// [`Simulator::rollout_from_codes`], [`Simulator::rollout_candidates`]): each predicted
    /// code becomes `mean + temperature * exp(S h + s) * noise` for a model with the spread
    /// head ([`Model::samples`]), the noise drawn from `seed`, the step and the item alone, so
    /// the same seed gives the same bits whatever the thread count or the batch. Temperature 0
    /// turns it off: the mean, bit for bit as without. A temperature below 0 or not finite is
    /// [`Error::Setting`]; above 0 on a model without the head, [`Error::NoSampling`].
    ///
    /// ```
    /// # use drivesim::{Config, Model, Simulator, WeightDtype};
    /// # let config = Config { height: 16, width: 32, base_channels: 2, z_dim: 8, hidden_dim: 8, ..Config::COMMA };
    /// let model = Model::random(&config, 1, WeightDtype::F32)?; // no spread head
    /// let mut sim = Simulator::new(&model)?;
    /// assert!(sim.set_sampling(1.0, 7).is_err());
    /// sim.set_sampling(0.0, 7)?; // the mean: always possible
    /// # Ok::<(), drivesim::Error>(())
    /// ```
    pub fn set_sampling(&mut self, temperature: f32, seed: u64) -> Result<()> {
        if !(temperature.is_finite() && temperature >= 0.0) {
            return Err(Error::Setting {
                name: "temperature",
                expected: "a finite number >= 0",
                value: temperature,
            });
        }
        if temperature > 0.0 && !self.model.borrow().samples() {
            return Err(Error::NoSampling);
        }
        self.sampling = Sampling { temperature, seed };
        Ok(())
    }

    /// The sampling's temperature and seed ([`Simulator::set_sampling`]); temperature 0: off.
    pub fn sampling(&self) -> (f32, u64) {
        (self.sampling.temperature, self.sampling.seed)
    }

    /// Turns the mean codes `codes` that a step predicted from the hidden states `h` it left
    /// (one per item, items numbered from 0) into the samples of rollout step `step`, as the
    /// rollouts do after each step: for a controller stepping the transition itself. Nothing
    /// changes with sampling off.
    pub fn sample(&mut self, h: &[f32], step: u64, codes: &mut [f32]) -> Result<()> {
        let c = *self.config();
        let n = self.batch_of("h", h, c.hidden_dim)?;
        expect_len("codes", codes, n * c.z_dim)?;
        expect_finite("h", h)?;
        expect_finite("codes", codes)?;
        let exec = Exec {
            isa: self.isa,
            pool: self.pool.as_ref(),
        };
        let model = self.model.borrow();
        sample_codes(&self.sampling, model, exec, &mut self.transition, h, step, codes);
        expect_finite_output("codes", codes)
    }
}

/// [`Simulator::sample`] of checked inputs (items numbered from 0): what the rollouts call.
pub(super) fn sample_codes(
    sampling: &Sampling,
    model: &Model,
    exec: Exec<'_>,
    buffers: &mut TransitionBuffers,
    h: &[f32],
    step: u64,
    codes: &mut [f32],
) {
    if sampling.is_on() {
        model.transition.sample(exec, buffers, sampling, h, step, codes);
    }
}
