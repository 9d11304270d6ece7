//! A [`TransitionTrainer`]'s state as bytes: everything a run needs to go on exactly where it
//! stopped (a checkpoint), into and from the caller's bytes, so that it needs no allocator.
//!
//! Layout (`weights/TRAINING_FILES.md`, "Checkpoints"): the 8 bytes `DSTRAN02`; `hidden_dim`, `z_dim`,
//! `action_dim`, whether the spread head is there (1 or 0) and the Adam steps taken, each a
//! little-endian u32; then little-endian f32: the packed weights (the spread head's last),
//! Adam's first and second moments (the arena's own layout) and the action normalisation (each
//! action's mean, then each's standard deviation).

use super::trainer::TransitionTrainer;
use crate::train::arena::{cut, cut_ref};
use crate::train::state::{read_state, state_len, write_state};
use crate::Result;

const MAGIC: &[u8; 8] = b"DSTRAN02";
/// The arena's buffers the state holds: weights, first and second moments, normalisation.
const SAVED: [usize; 4] = [0, 2, 3, 14];

impl TransitionTrainer<'_> {
    /// Bytes of [`TransitionTrainer::save_state`]'s state.
    pub fn state_len(&self) -> usize {
        state_len(5, SAVED.iter().map(|&i| self.plan.lens[i]).sum())
    }

    fn sizes(&self) -> [u32; 4] {
        let d = self.plan.dims;
        [d.hidden as u32, d.z as u32, d.actions as u32, d.spread as u32]
    }

    /// Writes the trainer's state into `out` ([`TransitionTrainer::state_len`] bytes): the
    /// weights, Adam's moments and step count, and the action normalisation. A trainer that
    /// [`TransitionTrainer::load_state`] reads it back goes on bit for bit as this one would
    /// (gradients computed but not applied are not kept: save between steps).
    pub fn save_state(&self, out: &mut [u8]) -> Result<()> {
        let buffers = cut_ref(self.memory.floats_ref(), &self.plan.lens);
        let [h, z, a, spread] = self.sizes();
        write_state(out, MAGIC, &[h, z, a, spread, self.steps()], &SAVED.map(|i| buffers[i]))
    }

    /// Restores a state [`TransitionTrainer::save_state`] wrote, for a transition of the same
    /// sizes (any batch, window or thread count). A state of other sizes, of another kind or
    /// truncated is [`crate::Error::Malformed`], one holding a non-finite value
    /// [`crate::Error::BadWeight`]; then the trainer is unchanged.
    pub fn load_state(&mut self, state: &[u8]) -> Result<()> {
        let (sizes, lens) = (self.sizes(), self.plan.lens);
        let [params, _, m, v, .., norm, _] = cut(self.memory.floats(), &lens);
        let steps = read_state(
            state,
            MAGIC,
            "transition trainer state",
            &sizes,
            &mut [params, m, v, norm],
        )?;
        self.restore_steps(steps);
        Ok(())
    }
}
