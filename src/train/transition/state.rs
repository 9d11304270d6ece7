//! A [`TransitionTrainer`]'s state as bytes: everything a run needs to go on exactly where it
//! stopped (a checkpoint), into and from the caller's bytes, so that it needs no allocator.
//!
//! Layout (`weights/README.md`, "Checkpoints"): the 8 bytes `DSTRAN01`; `hidden_dim`, `z_dim`,
//! `action_dim` and the Adam steps taken, each a little-endian u32; then little-endian f32: the
//! packed weights, Adam's first and second moments (the arena's own layout) and the action
//! normalisation (each action's mean, then each's standard deviation).

use super::trainer::TransitionTrainer;
use crate::error::expect_len;
use crate::train::arena::{cut, cut_ref};
use crate::{Error, Result};
use alloc::format;

const MAGIC: &[u8; 8] = b"DSTRAN01";
const HEADER: usize = MAGIC.len() + 4 * 4;
/// The arena's buffers the state holds: weights, first and second moments, normalisation.
const SAVED: [usize; 4] = [0, 2, 3, 14];

fn malformed(reason: alloc::string::String) -> Error {
    Error::Malformed {
        what: "transition trainer state",
        reason,
    }
}

impl TransitionTrainer<'_> {
    /// Bytes of [`TransitionTrainer::save_state`]'s state.
    pub fn state_len(&self) -> usize {
        HEADER + 4 * SAVED.iter().map(|&i| self.plan.lens[i]).sum::<usize>()
    }

    fn header(&self) -> [u32; 4] {
        let d = self.plan.dims;
        [d.hidden as u32, d.z as u32, d.actions as u32, self.steps()]
    }

    /// Writes the trainer's state into `out` ([`TransitionTrainer::state_len`] bytes): the
    /// weights, Adam's moments and step count, and the action normalisation. A trainer that
    /// [`TransitionTrainer::load_state`] reads it back goes on bit for bit as this one would
    /// (gradients computed but not applied are not kept: save between steps).
    pub fn save_state(&self, out: &mut [u8]) -> Result<()> {
        expect_len("out", out, self.state_len())?;
        let (header, mut rest) = out.split_at_mut(HEADER);
        header[..8].copy_from_slice(MAGIC);
        for (slot, value) in header[8..].chunks_exact_mut(4).zip(self.header()) {
            slot.copy_from_slice(&value.to_le_bytes());
        }
        let buffers = cut_ref(self.memory.floats_ref(), &self.plan.lens);
        for &i in &SAVED {
            let (bytes, tail) = rest.split_at_mut(4 * buffers[i].len());
            for (slot, value) in bytes.chunks_exact_mut(4).zip(buffers[i]) {
                slot.copy_from_slice(&value.to_le_bytes());
            }
            rest = tail;
        }
        Ok(())
    }

    /// Restores a state [`TransitionTrainer::save_state`] wrote, for a transition of the same
    /// sizes (any batch, window or thread count). A state of other sizes, of another kind or
    /// truncated is [`Error::Malformed`], one holding a non-finite value [`Error::BadWeight`];
    /// then the trainer is unchanged.
    pub fn load_state(&mut self, state: &[u8]) -> Result<()> {
        if state.len() != self.state_len() || !state.starts_with(MAGIC) {
            return Err(malformed(format!(
                "expected {} bytes beginning with {MAGIC:?}, found {}",
                self.state_len(),
                state.len()
            )));
        }
        let word =
            |i: usize| u32::from_le_bytes([state[8 + 4 * i], state[9 + 4 * i], state[10 + 4 * i], state[11 + 4 * i]]);
        let found = [word(0), word(1), word(2)];
        let expected = self.header();
        if found != expected[..3] {
            return Err(malformed(format!(
                "a transition of hidden_dim, z_dim, action_dim {found:?}, this trainer's are {:?}",
                &expected[..3]
            )));
        }
        let values = state[HEADER..]
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]));
        if let Some((index, value)) = values.clone().enumerate().find(|(_, v)| !v.is_finite()) {
            return Err(Error::BadWeight {
                name: "transition trainer state".into(),
                index,
                value,
                expected: "a finite number",
            });
        }
        let lens = self.plan.lens;
        let buffers = cut(self.memory.floats(), &lens);
        let mut values = values;
        for &i in &SAVED {
            buffers[i].iter_mut().zip(&mut values).for_each(|(slot, v)| *slot = v);
        }
        self.restore_steps(word(3));
        Ok(())
    }
}
