//! A [`VaeGanTrainer`]'s state as bytes: everything a run needs to go on exactly where it
//! stopped (a checkpoint), into and from the caller's bytes.
//!
//! Layout (`weights/TRAINING_FILES.md`, "Checkpoints"): the 8 bytes `DSVGAN01`; `height`, `width`,
//! `channels`, `base_channels`, `z_dim` and the Adam steps taken, each a little-endian u32; then
//! little-endian f32: the three networks' parameters (encoder, generator, discriminator, in the
//! trainer's layout), Adam's first and second moments in the same layout, and the running
//! statistics of every BatchNorm.

use super::trainer::VaeGanTrainer;
use crate::pool::Exec;
use crate::train::state::{read_state, state_len, write_state};
use crate::Result;

const MAGIC: &[u8; 8] = b"DSVGAN01";

impl VaeGanTrainer {
    /// Bytes of [`VaeGanTrainer::save_state`]'s state.
    pub fn state_len(&self) -> usize {
        let p = &self.parts;
        state_len(6, 3 * p.params.len() + p.stats.len())
    }

    fn sizes(&self) -> [u32; 5] {
        let c = &self.config;
        [c.height, c.width, c.channels, c.base_channels, c.z_dim].map(|v| v as u32)
    }

    /// Writes the trainer's state into `out` ([`VaeGanTrainer::state_len`] bytes): the
    /// encoder's, generator's and discriminator's weights, Adam's moments and step count, and
    /// the running statistics. A trainer that [`VaeGanTrainer::load_state`] reads it back goes
    /// on bit for bit as this one would.
    pub fn save_state(&self, out: &mut [u8]) -> Result<()> {
        let p = &self.parts;
        let [a, b, c, d, e] = self.sizes();
        let buffers = [&p.params[..], &p.moments[0], &p.moments[1], &p.stats];
        write_state(out, MAGIC, &[a, b, c, d, e, self.steps()], &buffers)
    }

    /// Restores a state [`VaeGanTrainer::save_state`] wrote, for the same frame size, channels
    /// and code size (any batch or thread count). A state of other sizes, of another kind or
    /// truncated is [`crate::Error::Malformed`], one holding a non-finite value
    /// [`crate::Error::BadWeight`]; then the trainer is unchanged.
    pub fn load_state(&mut self, state: &[u8]) -> Result<()> {
        let sizes = self.sizes();
        let p = &mut self.parts;
        let [m, v] = &mut p.moments;
        let buffers = &mut [&mut p.params[..], &mut m[..], &mut v[..], &mut p.stats[..]];
        let steps = read_state(state, MAGIC, "VAE-GAN trainer state", &sizes, buffers)?;
        p.saved_stats.copy_from_slice(&p.stats);
        let exec = Exec {
            isa: self.isa,
            pool: self.pool.as_ref(),
        };
        for net in 0..3 {
            self.parts.pack(net, exec);
        }
        self.steps = steps;
        Ok(())
    }
}
