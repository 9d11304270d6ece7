//! The per-network calls of a [`Simulator`]: encoding frames, generating frames and one
//! transition step (from given codes or fed its own prediction).

use super::Simulator;
use crate::error::{expect_finite, expect_finite_output, expect_frames, expect_len};
use crate::pool::Exec;
use crate::{Model, Result};
use core::borrow::Borrow;

impl<M: Borrow<Model>> Simulator<M> {
    /// Encodes frames to the VAE mean (the code used for simulation): one `z_dim` code per frame.
    pub fn encode(&mut self, frames: &[f32], z: &mut [f32]) -> Result<()> {
        self.encode_inner(frames, z, None)
    }

    /// Like [`Simulator::encode`], and also writes log-sigma (`tanh`-bounded) for each frame,
    /// for sampling `z = mean + exp(logsigma) * noise`.
    pub fn encode_with_logsigma(&mut self, frames: &[f32], mean: &mut [f32], logsigma: &mut [f32]) -> Result<()> {
        self.encode_inner(frames, mean, Some(logsigma))
    }

    fn encode_inner(&mut self, frames: &[f32], z: &mut [f32], logsigma: Option<&mut [f32]>) -> Result<()> {
        let n = self.batch_of("frames", frames, self.config().frame_len())?;
        let codes_len = n * self.config().z_dim;
        expect_len("z", z, codes_len)?;
        if let Some(logsigma) = logsigma.as_deref() {
            expect_len("logsigma", logsigma, codes_len)?;
        }
        expect_frames("frames", frames)?;
        let exec = Exec {
            isa: self.isa,
            pool: self.pool.as_ref(),
        };
        self.model
            .borrow()
            .encoder
            .forward(exec, &mut self.encoder, frames, z, logsigma);
        expect_finite_output("z", z)
    }

    /// Generates one frame per code, with values in [-1, 1].
    pub fn generate(&mut self, z: &[f32], frames: &mut [f32]) -> Result<()> {
        let n = self.batch_of("z", z, self.config().z_dim)?;
        expect_len("frames", frames, n * self.config().frame_len())?;
        expect_finite("z", z)?;
        let exec = Exec {
            isa: self.isa,
            pool: self.pool.as_ref(),
        };
        self.model
            .borrow()
            .generator
            .forward(exec, &mut self.generator, z, frames);
        expect_finite_output("frames", frames)
    }

    /// One transition step per code: updates the hidden states `h` in place and writes the
    /// predicted next codes to `z_next`. Start a sequence with `h` all zeros.
    pub fn transition(&mut self, z: &[f32], h: &mut [f32], action: &[f32], z_next: &mut [f32]) -> Result<()> {
        let c = *self.config();
        let n = self.batch_of("z", z, c.z_dim)?;
        expect_len("h", h, n * c.hidden_dim)?;
        expect_finite("z", z)?;
        self.step(n, h, Some(z), action, z_next)
    }

    /// One transition step per code fed its own prediction: the input code is the one `h`
    /// predicts, `A h + a` (what the step that left `h` wrote to its `z_next`), so `z` is
    /// not read but written: the predicted next codes. This is the step of a rollout after its
    /// seeds and of a controller's closed loop.
    ///
    /// `V z = V (A h + a)`, so with f32 weights the model folds `V A` into `W` at load and
    /// such a step reads a third fewer weights; with f16 weights it computes `A h + a` first.
    /// The result differs from [`Simulator::transition`] given that code only by rounding.
    ///
    /// ```
    /// # use drivesim::{Config, Model, Simulator, WeightDtype};
    /// # let config = Config { height: 16, width: 32, base_channels: 2, z_dim: 8, hidden_dim: 8, ..Config::COMMA };
    /// # let model = Model::random(&config, 1, WeightDtype::F32)?;
    /// let mut sim = Simulator::new(&model)?;
    /// let (seed, mut z, mut h) = (vec![0.1; 8], vec![0.0; 8], vec![0.0; 8]);
    /// sim.transition(&seed, &mut h, &[10.0, 0.0], &mut z)?; // from an encoded frame
    /// for steering in [0.1, 0.2, 0.3] {
    ///     sim.transition_fed_back(&mut h, &[10.0, steering], &mut z)?; // from its own prediction
    /// }
    /// # Ok::<(), drivesim::Error>(())
    /// ```
    pub fn transition_fed_back(&mut self, h: &mut [f32], action: &[f32], z: &mut [f32]) -> Result<()> {
        let c = *self.config();
        let n = self.batch_of("h", h, c.hidden_dim)?;
        self.step(n, h, None, action, z)
    }

    /// The checks and the step shared by [`Simulator::transition`] and
    /// [`Simulator::transition_fed_back`], for `n` items.
    fn step(&mut self, n: usize, h: &mut [f32], z: Option<&[f32]>, action: &[f32], z_next: &mut [f32]) -> Result<()> {
        let c = *self.config();
        expect_len("action", action, n * c.action_dim)?;
        expect_len("z_next", z_next, n * c.z_dim)?;
        expect_finite("h", h)?;
        expect_finite("action", action)?;
        let exec = Exec {
            isa: self.isa,
            pool: self.pool.as_ref(),
        };
        self.model
            .borrow()
            .transition
            .step(exec, &mut self.transition, h, z, action, z_next);
        expect_finite_output("h", h)?;
        expect_finite_output("z_next", z_next)
    }
}
