//! Rollouts of a [`Simulator`]: hallucinated drives seeded with frames or codes, and
//! [`Simulator::rollout_candidates`], many action sequences stepped in one batch (scored by
//! the reward and value heads in [`Simulator::rollout_candidates_scored`]).

use super::heads::{bound, gather, head_of, output_name};
use super::sampled::sample_codes;
use super::Simulator;
use crate::error::{expect_finite_output, expect_len};
use crate::heads::HeadKind;
use crate::pool::Exec;
use crate::{Model, Result};
use core::borrow::Borrow;

impl<M: Borrow<Model>> Simulator<M> {
    /// Hallucinates a drive: seeds the transition model with real frames, then feeds its own
    /// predictions back.
    ///
    /// There is one action per transition: step `i` maps frame `i` to frame `i + 1` with
    /// `actions[i]`. With `S` seed frames and `S - 1 + T` actions, the first `S - 1` steps are
    /// teacher-forced (their input is the encoded seed frame), step `S - 1` starts from the
    /// last seed frame's code, and every later step from the previous prediction. The `T`
    /// predicted codes (frames `S .. S + T`) go to `codes`; if `frames` is given, the generated
    /// frames go there too. The hidden state starts at zero. Steps from a prediction are
    /// [`Simulator::transition_fed_back`]'s.
    ///
    /// ```
    /// # use drivesim::{Config, Model, Simulator, WeightDtype};
    /// # let config = Config { height: 16, width: 32, base_channels: 2, z_dim: 8, hidden_dim: 8, ..Config::COMMA };
    /// # let model = Model::random(&config, 1, WeightDtype::F32)?;
    /// let mut sim = Simulator::new(&model)?;
    /// let seeds = vec![0.0; 3 * config.frame_len()]; // three frames
    /// let steps = 10;
    /// // 2 teacher-forced steps through the seeds, then 10 predictions: 12 (speed, steering).
    /// let actions: Vec<f32> = (0..2 + steps).flat_map(|t| [25.0, (t as f32 / 4.0).sin()]).collect();
    /// let mut codes = vec![0.0; steps * config.z_dim];
    /// let mut frames = vec![0.0; steps * config.frame_len()];
    /// sim.rollout(&seeds, &actions, &mut codes, Some(&mut frames))?;
    /// # Ok::<(), drivesim::Error>(())
    /// ```
    pub fn rollout(
        &mut self,
        seed_frames: &[f32],
        actions: &[f32],
        codes: &mut [f32],
        frames: Option<&mut [f32]>,
    ) -> Result<()> {
        self.run_rollout(Seeds::Frames(seed_frames), actions, codes, frames)
    }

    /// [`Simulator::rollout`] seeded with codes instead of frames, e.g. codes sampled from the
    /// encoder's `mean + exp(logsigma) * noise`.
    pub fn rollout_from_codes(
        &mut self,
        seed_codes: &[f32],
        actions: &[f32],
        codes: &mut [f32],
        frames: Option<&mut [f32]>,
    ) -> Result<()> {
        self.run_rollout(Seeds::Codes(seed_codes), actions, codes, frames)
    }

    /// Rolls out `candidates` action sequences at once from one state (or one state each):
    /// the planner's building block. Every candidate steps in one batch, so each step reads
    /// the transition's weights once for all of them.
    ///
    /// `h` is the hidden state of one step (`hidden_dim` values, shared by every candidate) or
    /// of one per candidate. The first step starts from `z` (the current code, `z_dim` values
    /// or one per candidate) where given, else from the code `h` predicts (as after a
    /// rollout's or [`Simulator::transition_fed_back`]'s last step); every later step from the
    /// candidate's previous prediction. Everything is **step-major**: `actions` holds `T`
    /// steps of `candidates` actions (`[T][candidates][action_dim]`), `codes` receives
    /// `[T][candidates][z_dim]` and `frames`, if given, `[T][candidates][frame]`. Each
    /// candidate gets the bits a rollout of its own would ([`Simulator::transition`] and
    /// [`Simulator::transition_fed_back`] step by step). `candidates` is at most the planned
    /// batch ([`Simulator::with_batch`]); `h` is not changed.
    ///
    /// ```
    /// # use drivesim::{Config, Model, Simulator, WeightDtype};
    /// # let config = Config { height: 16, width: 32, base_channels: 2, z_dim: 8, hidden_dim: 8, ..Config::COMMA };
    /// # let model = Model::random(&config, 1, WeightDtype::F32)?;
    /// let (candidates, steps) = (64, 10);
    /// let mut sim = Simulator::with_batch(&model, candidates)?;
    /// // The state after seeding: a rollout's hidden state and the real last code.
    /// let (h, z) = (vec![0.1; config.hidden_dim], vec![0.0; config.z_dim]);
    /// // Candidate n steers (n - 32) / 32 at every step, at speed 25.
    /// let actions: Vec<f32> = (0..steps * candidates)
    ///     .flat_map(|i| [25.0, ((i % candidates) as f32 - 32.0) / 32.0])
    ///     .collect();
    /// let mut codes = vec![0.0; steps * candidates * config.z_dim];
    /// sim.rollout_candidates(&h, Some(&z), candidates, &actions, &mut codes, None)?;
    /// # Ok::<(), drivesim::Error>(())
    /// ```
    pub fn rollout_candidates(
        &mut self,
        h: &[f32],
        z: Option<&[f32]>,
        candidates: usize,
        actions: &[f32],
        codes: &mut [f32],
        frames: Option<&mut [f32]>,
    ) -> Result<()> {
        let steps = self.check_candidates(h, z, candidates, actions, codes, frames.as_deref())?;
        self.candidates(steps, h, z, candidates, actions, codes, frames, None)
    }

    /// [`Simulator::rollout_candidates`] with the model's reward and value heads read after
    /// every step, in the same batch: the planner's scores. `rewards` receives
    /// `[T][candidates][2]`, each step's `(reward, off-road chance)` ([`Simulator::reward`]
    /// of the state the step reached), and `values` `[T][candidates]`, the value of that state
    /// ([`Simulator::value`]). A model without both heads is [`crate::Error::NoHead`].
    ///
    /// ```
    /// # use drivesim::{Config, Model, Simulator};
    /// # let model = drivesim::Model::load("weights/default.safetensors")?;
    /// # if model.head_width(drivesim::HeadKind::Value).is_none() { return Ok(()); }
    /// let c = *model.config();
    /// let (candidates, steps) = (16, 8);
    /// let mut sim = Simulator::with_batch(&model, candidates)?;
    /// let (h, z) = (vec![0.0; c.hidden_dim], vec![0.0; c.z_dim]);
    /// let actions: Vec<f32> = (0..steps * candidates).flat_map(|i| [40.0, (i % 3) as f32 * 0.2 - 0.2]).collect();
    /// let mut codes = vec![0.0; steps * candidates * c.z_dim];
    /// let (mut rewards, mut values) = (vec![0.0; steps * candidates * 2], vec![0.0; steps * candidates]);
    /// sim.rollout_candidates_scored(&h, Some(&z), candidates, &actions, &mut codes, &mut rewards, &mut values)?;
    /// # Ok::<(), drivesim::Error>(())
    /// ```
    #[allow(clippy::too_many_arguments)] // rollout_candidates' own, and the two outputs
    pub fn rollout_candidates_scored(
        &mut self,
        h: &[f32],
        z: Option<&[f32]>,
        candidates: usize,
        actions: &[f32],
        codes: &mut [f32],
        rewards: &mut [f32],
        values: &mut [f32],
    ) -> Result<()> {
        let steps = self.check_candidates(h, z, candidates, actions, codes, None)?;
        let model = self.model.borrow();
        head_of(model, HeadKind::Reward)?;
        head_of(model, HeadKind::Value)?;
        expect_len("rewards", rewards, steps * candidates * 2)?;
        expect_len("values", values, steps * candidates)?;
        let scores = Some(Scores { rewards, values });
        self.candidates(steps, h, z, candidates, actions, codes, None, scores)
    }

    /// The rollout of [`Simulator::rollout_candidates`] and
    /// [`Simulator::rollout_candidates_scored`], `steps` long, on arguments they checked.
    #[allow(clippy::too_many_arguments)]
    fn candidates(
        &mut self,
        steps: usize,
        h: &[f32],
        z: Option<&[f32]>,
        candidates: usize,
        actions: &[f32],
        codes: &mut [f32],
        mut frames: Option<&mut [f32]>,
        mut scores: Option<Scores<'_>>,
    ) -> Result<()> {
        let c = *self.config();
        let n = candidates;
        let step_len = n * c.action_dim;

        let exec = Exec {
            isa: self.isa,
            pool: self.pool.as_ref(),
        };
        let model = self.model.borrow();
        // From one state and one code (or none), the first step sums the state's part once.
        let shared = h.len() == c.hidden_dim && z.is_none_or(|z| z.len() == c.z_dim);
        let hs = &mut self.rollout_h[..n * c.hidden_dim];
        let first = &mut self.rollout_z[0][..n * c.z_dim];
        if !shared {
            for state in hs.chunks_exact_mut(h.len()) {
                state.copy_from_slice(h);
            }
            if let Some(z) = z {
                for code in first.chunks_exact_mut(z.len()) {
                    code.copy_from_slice(z);
                }
            }
        }
        // Sampled codes are not what `h` predicts: every step then takes its input.
        let (len, sampling) = (n * c.z_dim, self.sampling);
        let folds = model.transition.folds() && !sampling.is_on();
        for t in 0..steps {
            let (done, rest) = codes.split_at_mut(t * len);
            let out = &mut rest[..len];
            let input = match t {
                0 => z.map(|_| &first[..]),
                // An unfolded model would recompute the previous prediction: give it that.
                _ if !folds => Some(&done[(t - 1) * len..]),
                _ => None,
            };
            let action = &actions[t * step_len..][..step_len];
            let transition = &model.transition;
            match t {
                0 if shared => transition.step_shared(exec, &mut self.transition, h, z, action, hs, out),
                _ => transition.step(exec, &mut self.transition, hs, input, action, out),
            }
            sample_codes(&sampling, model, exec, &mut self.transition, hs, t as u64, out);
            expect_finite_output("codes", out)?;
            if let Some(scores) = scores.as_mut() {
                let inputs = &mut self.transition.concat()[..n * (c.z_dim + c.hidden_dim)];
                gather(&c, out, hs, inputs);
                let outputs = [
                    (HeadKind::Reward, &mut scores.rewards[t * n * 2..][..n * 2]),
                    (HeadKind::Value, &mut scores.values[t * n..][..n]),
                ];
                for (kind, out) in outputs {
                    let head = head_of(model, kind)?;
                    head.run(exec, inputs, &mut self.head_hidden[..n * head.width()], out);
                    expect_finite_output(output_name(kind), out)?;
                    bound(model, kind, out);
                }
            }
            if let Some(frames) = frames.as_deref_mut() {
                let frames = &mut frames[t * n * c.frame_len()..][..n * c.frame_len()];
                model.generator.forward(exec, &mut self.generator, out, frames);
                expect_finite_output("frames", frames)?;
            }
        }
        Ok(())
    }

    /// The rollout of [`Simulator::rollout`] and [`Simulator::rollout_from_codes`].
    fn run_rollout(
        &mut self,
        seeds: Seeds<'_>,
        actions: &[f32],
        codes: &mut [f32],
        mut frames: Option<&mut [f32]>,
    ) -> Result<()> {
        let c = *self.config();
        let (seed_count, item_len) = self.check_rollout(seeds, actions, codes, frames.as_deref())?;

        let exec = Exec {
            isa: self.isa,
            pool: self.pool.as_ref(),
        };
        // An unfolded model's fed-back step would recompute `A h + a`: the last prediction,
        // bit for bit (the kernels sum in one order whatever the split), so give it that.
        // Sampled codes are not what `h` predicts: every step then takes its input.
        let sampling = self.sampling;
        let folds = self.model.borrow().transition.folds() && !sampling.is_on();
        let h = &mut self.rollout_h[..c.hidden_dim];
        h.fill(0.0);
        let [z, z_next] = &mut self.rollout_z;
        let z = &mut z[..c.z_dim];
        for (step, action) in actions.chunks_exact(c.action_dim).enumerate() {
            let fed_back = step >= seed_count;
            match seeds {
                _ if fed_back => z.copy_from_slice(z_next),
                Seeds::Frames(f) => self.model.borrow().encoder.forward(
                    exec,
                    &mut self.encoder,
                    &f[step * item_len..][..item_len],
                    z,
                    None,
                ),
                Seeds::Codes(codes) => z.copy_from_slice(&codes[step * item_len..][..item_len]),
            }
            let input = if fed_back && folds { None } else { Some(&z[..]) };
            self.model
                .borrow()
                .transition
                .step(exec, &mut self.transition, h, input, action, z_next);
            if let Some(t) = (step + 1).checked_sub(seed_count) {
                let model = self.model.borrow();
                sample_codes(&sampling, model, exec, &mut self.transition, h, t as u64, z_next);
                codes[t * c.z_dim..][..c.z_dim].copy_from_slice(z_next);
                if let Some(frames) = frames.as_deref_mut() {
                    let frame = &mut frames[t * c.frame_len()..][..c.frame_len()];
                    self.model
                        .borrow()
                        .generator
                        .forward(exec, &mut self.generator, z_next, frame);
                    expect_finite_output("frames", frame)?;
                }
            }
            expect_finite_output("codes", z_next)?;
        }
        Ok(())
    }
}

/// Where a scored candidate rollout writes its heads' outputs: `[T][n][2]` and `[T][n]`.
struct Scores<'a> {
    rewards: &'a mut [f32],
    values: &'a mut [f32],
}

/// What a rollout is seeded with.
#[derive(Clone, Copy)]
pub(super) enum Seeds<'a> {
    Frames(&'a [f32]),
    Codes(&'a [f32]),
}
