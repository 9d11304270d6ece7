//! Drives inside the simulator that a controller steps: the hidden state and the current code
//! of each kept inside, as a gym-style environment keeps its state.

use crate::error::{expect_finite, expect_len};
use crate::{Error, Model, Result, Simulator};
use alloc::vec::Vec;
use core::borrow::Borrow;

/// `drives` simulated drives stepping together: reset from real frames (or codes), then each
/// [`Environment::step`] applies one action per drive and moves every drive to its next
/// predicted code, in one batch (the drives share each pass over the weights). The model is
/// borrowed or owned as by [`Simulator`]; nothing allocates after [`Environment::new`].
///
/// ```
/// use drivesim::{Config, Environment, Model, WeightDtype};
///
/// # fn main() -> Result<(), drivesim::Error> {
/// let config = Config { height: 16, width: 32, base_channels: 2, z_dim: 8, hidden_dim: 8, ..Config::COMMA };
/// let model = Model::random(&config, 1, WeightDtype::F32)?;
/// let (drives, seeds) = (2, 3);
/// let mut env = Environment::new(model, drives, 16)?; // owns the model; 16 candidates at most
/// // Seed frames step by step ([seed][drive][frame]) and the actions between them.
/// let frames = vec![0.0; seeds * drives * config.frame_len()];
/// env.reset_from_frames(&frames, &vec![25.0; (seeds - 1) * drives * 2])?;
/// let mut picture = vec![0.0; drives * config.frame_len()];
/// for t in 0..10 {
///     let steer = (t as f32 / 3.0).sin();
///     env.step(&[25.0, steer, 25.0, -steer])?; // (speed, steering) per drive
///     env.frames(&mut picture)?;
/// }
/// assert_eq!(env.codes().len(), drives * config.z_dim);
/// # Ok(())
/// # }
/// ```
pub struct Environment<M: Borrow<Model>> {
    sim: Simulator<M>,
    drives: usize,
    /// `[drive][hidden_dim]`.
    hidden: Vec<f32>,
    /// `[drive][z_dim]`: the code of each drive's current frame.
    codes: Vec<f32>,
    /// The next codes of a step from given codes.
    next: Vec<f32>,
    /// Whether `codes` are the hidden states' own predictions (after a step), so that steps
    /// take the fed-back path, or real codes (after a reset).
    predicted: bool,
    /// Whether a reset has given every drive a state.
    seeded: bool,
    /// Steps since the last reset: the step of a sampled step's noise.
    steps: u64,
}

impl<M: Borrow<Model>> Environment<M> {
    /// `drives` drives of `model`, with room for rollouts of up to `candidates` action
    /// sequences ([`Environment::rollout_candidates`]). Plans and allocates everything once.
    pub fn new(model: M, drives: usize, candidates: usize) -> Result<Self> {
        let c = *model.borrow().config();
        if drives == 0 {
            return Err(Error::Config {
                field: "drives",
                expected: "at least 1",
                found: 0,
            });
        }
        let sim = Simulator::with_batch(model, drives.max(candidates))?;
        let zeros = |n: usize| crate::plan::zeros(n, sim.buffer_bytes());
        Ok(Environment {
            hidden: zeros(drives * c.hidden_dim)?,
            codes: zeros(drives * c.z_dim)?,
            next: zeros(drives * c.z_dim)?,
            sim,
            drives,
            predicted: false,
            seeded: false,
            steps: 0,
        })
    }

    /// Shares each step among `threads` threads (see [`Simulator::with_threads`]).
    #[cfg(feature = "std")]
    pub fn with_threads(mut self, threads: usize) -> Result<Self> {
        self.sim = self.sim.with_threads(threads)?;
        Ok(self)
    }

    /// The simulator underneath, for encoding or generating besides the drives.
    pub fn simulator(&mut self) -> &mut Simulator<M> {
        &mut self.sim
    }

    /// Resets every drive from seed codes, step-major (`[seed][drive][z_dim]`, at least one
    /// seed), with the actions between consecutive seeds (`[seed - 1][drive][action_dim]`):
    /// the hidden state starts at zero and runs through the seeds teacher-forced, and the last
    /// seed becomes the current code, as in [`Simulator::rollout`].
    pub fn reset_from_codes(&mut self, codes: &[f32], actions: &[f32]) -> Result<()> {
        let c = *self.sim.config();
        let seeds = self.seed_count("codes", codes, c.z_dim, actions)?;
        // The last seed becomes the current code without a transition step to check it.
        expect_finite("codes", codes)?;
        self.hidden.fill(0.0);
        (self.seeded, self.steps) = (false, 0);
        let per_seed = self.codes.len();
        for s in 0..seeds {
            self.codes.copy_from_slice(&codes[s * per_seed..][..per_seed]);
            self.teacher_step(s, seeds, actions)?;
        }
        self.seeded = true;
        Ok(())
    }

    /// [`Environment::reset_from_codes`] from seed frames (`[seed][drive][frame]`), encoded
    /// here (the encoder's means).
    pub fn reset_from_frames(&mut self, frames: &[f32], actions: &[f32]) -> Result<()> {
        let c = *self.sim.config();
        let seeds = self.seed_count("frames", frames, c.frame_len(), actions)?;
        self.hidden.fill(0.0);
        (self.seeded, self.steps) = (false, 0);
        let per_seed = self.drives * c.frame_len();
        for s in 0..seeds {
            self.sim.encode(&frames[s * per_seed..][..per_seed], &mut self.codes)?;
            self.teacher_step(s, seeds, actions)?;
        }
        self.seeded = true;
        Ok(())
    }

    /// The number of seeds in `data` (`[seed][drive][item_len]`), checked against `actions`.
    fn seed_count(&self, buffer: &'static str, data: &[f32], item_len: usize, actions: &[f32]) -> Result<usize> {
        let per_seed = self.drives * item_len;
        if data.is_empty() || !data.len().is_multiple_of(per_seed) {
            return Err(Error::NotWholeItems {
                buffer,
                item_len: per_seed,
                found: data.len(),
            });
        }
        let seeds = data.len() / per_seed;
        expect_len(
            "actions",
            actions,
            (seeds - 1) * self.drives * self.sim.config().action_dim,
        )?;
        Ok(seeds)
    }

    /// Seed `s` of `seeds` is in `codes`: all but the last step the hidden state with it.
    fn teacher_step(&mut self, s: usize, seeds: usize, actions: &[f32]) -> Result<()> {
        self.predicted = false;
        if s + 1 < seeds {
            let per_step = self.drives * self.sim.config().action_dim;
            let action = &actions[s * per_step..][..per_step];
            self.sim
                .transition(&self.codes, &mut self.hidden, action, &mut self.next)?;
        }
        Ok(())
    }

    /// Samples every later step's codes and rollouts ([`Simulator::set_sampling`]): a step's
    /// noise is that of the steps since the last reset and the drive, so a reset and the same
    /// actions give the same drive again. Temperature 0: the mean.
    pub fn set_sampling(&mut self, temperature: f32, seed: u64) -> Result<()> {
        self.sim.set_sampling(temperature, seed)
    }

    /// One step of every drive: `actions` holds one action per drive (`[drive][action_dim]`);
    /// each drive's current code becomes its predicted next one (a sample of it with sampling
    /// on, [`Environment::set_sampling`]). Bad actions are refused before anything changes; a
    /// step that fails after that (a prediction that is not finite) leaves the drives needing
    /// a reset ([`Error::NotSeeded`] until then), never half a step.
    pub fn step(&mut self, actions: &[f32]) -> Result<()> {
        self.expect_seeded()?;
        expect_len("actions", actions, self.drives * self.sim.config().action_dim)?;
        expect_finite("actions", actions)?;
        let stepped = self.advance(actions);
        if stepped.is_err() {
            self.seeded = false;
        }
        stepped
    }

    /// [`Environment::step`] of checked actions.
    fn advance(&mut self, actions: &[f32]) -> Result<()> {
        if self.sim.sampling().0 > 0.0 {
            // A sample is not what the hidden state predicts: step from it.
            self.sim
                .transition(&self.codes, &mut self.hidden, actions, &mut self.next)?;
            self.sim.sample(&self.hidden, self.steps, &mut self.next)?;
            core::mem::swap(&mut self.codes, &mut self.next);
            self.predicted = false;
        } else if self.predicted {
            self.sim
                .transition_fed_back(&mut self.hidden, actions, &mut self.codes)?;
        } else {
            self.sim
                .transition(&self.codes, &mut self.hidden, actions, &mut self.next)?;
            core::mem::swap(&mut self.codes, &mut self.next);
            self.predicted = true;
        }
        self.steps += 1;
        Ok(())
    }

    /// Whether a reset gave the drives a state (false before the first and after a failed
    /// one): until then [`Environment::step`] and [`Environment::frames`] are
    /// [`Error::NotSeeded`], and [`Environment::codes`] and [`Environment::hidden`] are zeros.
    pub fn is_seeded(&self) -> bool {
        self.seeded
    }

    /// The current code of every drive, `[drive][z_dim]`.
    pub fn codes(&self) -> &[f32] {
        &self.codes
    }

    /// The hidden state of every drive, `[drive][hidden_dim]`.
    pub fn hidden(&self) -> &[f32] {
        &self.hidden
    }

    /// The current frame of every drive, generated from its code into `frames`
    /// (`[drive][frame]`).
    pub fn frames(&mut self, frames: &mut [f32]) -> Result<()> {
        self.expect_seeded()?;
        self.sim.generate(&self.codes, frames)
    }

    /// Rolls out `candidates` action sequences from drive `drive`'s current state without
    /// changing it: [`Simulator::rollout_candidates`] (step-major `actions`, `codes` and
    /// optional `frames`), the first step as [`Environment::step`] would take it.
    pub fn rollout_candidates(
        &mut self,
        drive: usize,
        candidates: usize,
        actions: &[f32],
        codes: &mut [f32],
        frames: Option<&mut [f32]>,
    ) -> Result<()> {
        self.expect_seeded()?;
        if drive >= self.drives {
            return Err(Error::OutOfRange {
                what: "drive",
                index: drive,
                len: self.drives,
            });
        }
        let c = *self.sim.config();
        let h = &self.hidden[drive * c.hidden_dim..][..c.hidden_dim];
        let z = (!self.predicted).then(|| &self.codes[drive * c.z_dim..][..c.z_dim]);
        self.sim.rollout_candidates(h, z, candidates, actions, codes, frames)
    }

    fn expect_seeded(&self) -> Result<()> {
        match self.seeded {
            true => Ok(()),
            false => Err(Error::NotSeeded),
        }
    }
}
