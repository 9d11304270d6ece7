//! Running the networks in buffers planned once.

use crate::encoder::EncoderBuffers;
use crate::error::{expect_finite, expect_len};
use crate::generator::GeneratorBuffers;
use crate::pool::{Exec, Pool};
use crate::transition::TransitionBuffers;
use crate::{Config, Error, Model, Result};
use alloc::vec::Vec;
use drivesim_kernels::Isa;

/// Runs a [`Model`]: encodes frames, steps the transition model, generates frames, and rolls
/// the three together into a hallucinated drive.
///
/// Every buffer is allocated by [`Simulator::new`] / [`Simulator::with_batch`]; after that no
/// method allocates. Frames are `&[f32]` of `height * width * channels` values in HWC order
/// (pixel-interleaved RGB) scaled to [-1, 1]; codes are `z_dim` values; actions are
/// `action_dim` values, (speed, steering) for the comma config. Methods that take several
/// frames, codes or actions take them back to back in one slice, up to the planned batch.
pub struct Simulator<'m> {
    model: &'m Model,
    isa: Isa,
    /// Threads that share each convolution and large dense layer (none: the caller's alone).
    pool: Option<Pool>,
    max_batch: usize,
    encoder: EncoderBuffers,
    generator: GeneratorBuffers,
    transition: TransitionBuffers,
    /// Hidden state and codes of a rollout.
    rollout_h: Vec<f32>,
    rollout_z: [Vec<f32>; 2],
}

impl<'m> Simulator<'m> {
    /// A simulator for one frame or code per call.
    pub fn new(model: &'m Model) -> Self {
        Simulator::with_batch(model, 1)
    }

    /// A simulator for up to `max_batch` frames or codes per call (at least 1). Batches
    /// share each pass over the dense layers' weights, which dominate at batch 1.
    pub fn with_batch(model: &'m Model, max_batch: usize) -> Self {
        let max_batch = max_batch.max(1);
        let c = model.config();
        Simulator {
            model,
            isa: Isa::best(),
            pool: None,
            max_batch,
            encoder: model.encoder.buffers(max_batch, 1, 1),
            generator: model.generator.buffers(max_batch, 1, 1),
            transition: model.transition.buffers(max_batch),
            rollout_h: alloc::vec![0.0; c.hidden_dim],
            rollout_z: [alloc::vec![0.0; c.z_dim], alloc::vec![0.0; c.z_dim]],
        }
    }

    /// Uses the kernels of `isa` instead of the best this CPU has (e.g. to compare paths).
    pub fn with_isa(mut self, isa: Isa) -> Self {
        self.isa = isa;
        self
    }

    /// Shares the work of each call among `threads` threads (the caller's included), started
    /// here once and kept until the simulator is dropped. Calls still allocate nothing.
    ///
    /// A single frame or code is shared layer by layer: each convolution by blocks of output
    /// channels, each large dense layer (the transition's included) by rows. A batch of at
    /// least `threads` items is shared item by item instead, so this also plans a set of
    /// activation planes per thread when the planned batch is above 1 (see
    /// [`Simulator::buffer_bytes`]).
    #[cfg(feature = "std")]
    pub fn with_threads(mut self, threads: usize) -> Result<Self> {
        self.pool = match threads {
            0 | 1 => None,
            n => Some(Pool::new(n).map_err(|source| Error::Threads { requested: n, source })?),
        };
        let sets = if self.max_batch > 1 { self.threads() } else { 1 };
        self.encoder = self.model.encoder.buffers(self.max_batch, sets, self.threads());
        self.generator = self.model.generator.buffers(self.max_batch, sets, self.threads());
        Ok(self)
    }

    /// Threads that share each frame's work, the caller's included.
    pub fn threads(&self) -> usize {
        self.pool.as_ref().map_or(1, Pool::threads)
    }

    /// The instruction set the kernels run with.
    pub fn isa(&self) -> Isa {
        self.isa
    }

    pub fn config(&self) -> &Config {
        self.model.config()
    }

    /// Bytes of the buffers this simulator allocated when it was planned: all the memory its
    /// calls use besides the model's weights (and a few hundred bytes of bookkeeping).
    pub fn buffer_bytes(&self) -> usize {
        let rollout = self.rollout_h.len() + self.rollout_z.iter().map(Vec::len).sum::<usize>();
        let floats = self.encoder.len() + self.generator.len() + self.transition.len() + rollout;
        floats * core::mem::size_of::<f32>()
    }

    /// The largest batch one call takes.
    pub fn max_batch(&self) -> usize {
        self.max_batch
    }

    /// How many items of `item_len` values `data` holds: a whole, non-zero number, at most the batch.
    fn batch_of(&self, buffer: &'static str, data: &[f32], item_len: usize) -> Result<usize> {
        if data.is_empty() || !data.len().is_multiple_of(item_len) {
            return Err(Error::NotWholeItems {
                buffer,
                item_len,
                found: data.len(),
            });
        }
        let n = data.len() / item_len;
        if n > self.max_batch {
            return Err(Error::BatchTooLarge {
                max: self.max_batch,
                found: n,
            });
        }
        Ok(n)
    }

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
        expect_finite("frames", frames)?;
        let exec = Exec {
            isa: self.isa,
            pool: self.pool.as_ref(),
        };
        self.model.encoder.forward(exec, &mut self.encoder, frames, z, logsigma);
        Ok(())
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
        self.model.generator.forward(exec, &mut self.generator, z, frames);
        Ok(())
    }

    /// One transition step per code: updates the hidden states `h` in place and writes the
    /// predicted next codes to `z_next`. Start a sequence with `h` all zeros.
    ///
    /// A model fed its own predictions (`z` is the `z_next` of this simulator's last call, and
    /// `h` what that call left) needs no `V`: `V z = V (A h + a)`, so with f32 weights the model
    /// folds `V A` into `W` at load and such a step reads a third fewer weights. The simulator
    /// recognises these steps by comparing `h` and `z` with what its last step wrote. The
    /// result differs from the two-product step only by rounding.
    ///
    /// ```
    /// # use drivesim::{Config, Model, Simulator, WeightDtype};
    /// # let config = Config { height: 16, width: 32, base_channels: 2, z_dim: 8, hidden_dim: 8, ..Config::COMMA };
    /// # let model = Model::random(&config, 1, WeightDtype::F32)?;
    /// let mut sim = Simulator::new(&model);
    /// let (mut z, mut z_next, mut h) = (vec![0.1; 8], vec![0.0; 8], vec![0.0; 8]);
    /// for steering in [0.0, 0.1, 0.2] {
    ///     sim.transition(&z, &mut h, &[10.0, steering], &mut z_next)?;
    ///     // Fed back: every step after the first is the folded one.
    ///     std::mem::swap(&mut z, &mut z_next);
    /// }
    /// # Ok::<(), drivesim::Error>(())
    /// ```
    pub fn transition(&mut self, z: &[f32], h: &mut [f32], action: &[f32], z_next: &mut [f32]) -> Result<()> {
        let c = *self.config();
        let n = self.batch_of("z", z, c.z_dim)?;
        expect_len("h", h, n * c.hidden_dim)?;
        expect_len("action", action, n * c.action_dim)?;
        expect_len("z_next", z_next, n * c.z_dim)?;
        expect_finite("z", z)?;
        expect_finite("h", h)?;
        expect_finite("action", action)?;
        let exec = Exec {
            isa: self.isa,
            pool: self.pool.as_ref(),
        };
        self.model
            .transition
            .step(exec, &mut self.transition, h, z, action, z_next);
        Ok(())
    }

    /// Hallucinates a drive: seeds the transition model with real frames, then feeds its own
    /// predictions back.
    ///
    /// There is one action per transition: step `i` maps frame `i` to frame `i + 1` with
    /// `actions[i]`. With `S` seed frames and `S - 1 + T` actions, the first `S - 1` steps are
    /// teacher-forced (their input is the encoded seed frame), step `S - 1` starts from the
    /// last seed frame's code, and every later step from the previous prediction. The `T`
    /// predicted codes (frames `S .. S + T`) go to `codes`; if `frames` is given, the generated
    /// frames go there too. The hidden state starts at zero. Steps from a prediction take the
    /// folded form described at [`Simulator::transition`].
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

    fn run_rollout(
        &mut self,
        seeds: Seeds<'_>,
        actions: &[f32],
        codes: &mut [f32],
        mut frames: Option<&mut [f32]>,
    ) -> Result<()> {
        let c = *self.config();
        let (buffer, data, item_len) = match seeds {
            Seeds::Frames(f) => ("seed_frames", f, c.frame_len()),
            Seeds::Codes(z) => ("seed_codes", z, c.z_dim),
        };
        if data.is_empty() || data.len() % item_len != 0 {
            return Err(Error::NotWholeItems {
                buffer,
                item_len,
                found: data.len(),
            });
        }
        if !actions.len().is_multiple_of(c.action_dim) {
            return Err(Error::NotWholeItems {
                buffer: "actions",
                item_len: c.action_dim,
                found: actions.len(),
            });
        }
        let seed_count = data.len() / item_len;
        let steps = actions.len() / c.action_dim;
        let predicted = steps
            .checked_sub(seed_count - 1)
            .filter(|&t| t > 0)
            .ok_or(Error::BufferLength {
                buffer: "actions",
                expected: seed_count * c.action_dim,
                found: actions.len(),
            })?;
        expect_len("codes", codes, predicted * c.z_dim)?;
        if let Some(frames) = frames.as_deref() {
            expect_len("frames", frames, predicted * c.frame_len())?;
        }
        expect_finite(buffer, data)?;
        expect_finite("actions", actions)?;

        let exec = Exec {
            isa: self.isa,
            pool: self.pool.as_ref(),
        };
        self.rollout_h.fill(0.0);
        let [z, z_next] = &mut self.rollout_z;
        for (step, action) in actions.chunks_exact(c.action_dim).enumerate() {
            match seeds {
                _ if step >= seed_count => core::mem::swap(z, z_next),
                Seeds::Frames(f) => {
                    self.model
                        .encoder
                        .forward(exec, &mut self.encoder, &f[step * item_len..][..item_len], z, None)
                }
                Seeds::Codes(codes) => z.copy_from_slice(&codes[step * item_len..][..item_len]),
            }
            self.model
                .transition
                .step(exec, &mut self.transition, &mut self.rollout_h, z, action, z_next);
            if let Some(t) = (step + 1).checked_sub(seed_count) {
                codes[t * c.z_dim..][..c.z_dim].copy_from_slice(z_next);
                if let Some(frames) = frames.as_deref_mut() {
                    let frame = &mut frames[t * c.frame_len()..][..c.frame_len()];
                    self.model.generator.forward(exec, &mut self.generator, z_next, frame);
                }
            }
        }
        Ok(())
    }
}

/// What a rollout is seeded with.
#[derive(Clone, Copy)]
enum Seeds<'a> {
    Frames(&'a [f32]),
    Codes(&'a [f32]),
}
