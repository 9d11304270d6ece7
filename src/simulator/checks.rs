//! The input checks of a [`Simulator`]'s calls: whole items within the planned batch, and the
//! buffers of a rollout and of candidate rollouts, checked before anything runs.

use super::rollout::Seeds;
use super::Simulator;
use crate::error::{expect_finite, expect_frames, expect_len, whole_items};
use crate::{Error, Model, Result};
use core::borrow::Borrow;

impl<M: Borrow<Model>> Simulator<M> {
    /// How many items of `item_len` values `data` holds: a whole, non-zero number, at most the batch.
    pub(super) fn batch_of(&self, buffer: &'static str, data: &[f32], item_len: usize) -> Result<usize> {
        let n = whole_items(buffer, data, item_len)?;
        if n > self.max_batch() {
            return Err(Error::BatchTooLarge {
                max: self.max_batch(),
                found: n,
            });
        }
        Ok(n)
    }

    /// The checks of [`Simulator::rollout`] and [`Simulator::rollout_from_codes`]: the seed
    /// count and the values per seed.
    pub(super) fn check_rollout(
        &self,
        seeds: Seeds<'_>,
        actions: &[f32],
        codes: &[f32],
        frames: Option<&[f32]>,
    ) -> Result<(usize, usize)> {
        let c = *self.config();
        let (buffer, data, item_len) = match seeds {
            Seeds::Frames(f) => ("seed_frames", f, c.frame_len()),
            Seeds::Codes(z) => ("seed_codes", z, c.z_dim),
        };
        let seed_count = whole_items(buffer, data, item_len)?;
        if !actions.len().is_multiple_of(c.action_dim) {
            return Err(Error::NotWholeItems {
                buffer: "actions",
                item_len: c.action_dim,
                found: actions.len(),
            });
        }
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
        if let Some(frames) = frames {
            expect_len("frames", frames, predicted * c.frame_len())?;
        }
        match seeds {
            Seeds::Frames(f) => expect_frames(buffer, f)?,
            Seeds::Codes(z) => expect_finite(buffer, z)?,
        }
        expect_finite("actions", actions)?;
        Ok((seed_count, item_len))
    }

    /// The checks of [`Simulator::rollout_candidates`] for `n` candidates: the steps.
    pub(super) fn check_candidates(
        &self,
        h: &[f32],
        z: Option<&[f32]>,
        n: usize,
        actions: &[f32],
        codes: &[f32],
        frames: Option<&[f32]>,
    ) -> Result<usize> {
        let c = *self.config();
        if n == 0 || n > self.max_batch() {
            return Err(Error::BatchTooLarge {
                max: self.max_batch(),
                found: n,
            });
        }
        // One value set for all candidates, or one each.
        let each = |buffer, data: &[f32], len: usize| match data.len() {
            l if l == len || l == n * len => Ok(()),
            found => Err(Error::BufferLength {
                buffer,
                expected: n * len,
                found,
            }),
        };
        each("h", h, c.hidden_dim)?;
        if let Some(z) = z {
            each("z", z, c.z_dim)?;
            expect_finite("z", z)?;
        }
        let steps = whole_items("actions", actions, n * c.action_dim)?;
        expect_len("codes", codes, steps * n * c.z_dim)?;
        if let Some(frames) = frames {
            expect_len("frames", frames, steps * n * c.frame_len())?;
        }
        expect_finite("h", h)?;
        expect_finite("actions", actions)?;
        Ok(steps)
    }
}
