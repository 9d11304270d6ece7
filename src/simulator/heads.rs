//! The heads of a [`Simulator`]'s model ([`crate::HeadKind`]): the policy's actions, the
//! reward head's rewards and off-road chances, the value head's values, for a batch of states.

use super::Simulator;
use crate::error::{expect_finite, expect_finite_output, expect_len};
use crate::heads::{Head, HeadKind};
use crate::pool::Exec;
use crate::{Config, Error, Model, Result};
use core::borrow::Borrow;

impl<M: Borrow<Model>> Simulator<M> {
    /// The cloned driver's actions (the model's policy, `policy.*` tensors): for each item, the
    /// action a driver would take seeing the frame encoded as `z`, with the transition's hidden
    /// state `h` after the drive's earlier codes and actions (from zeros at its first frame,
    /// as [`Simulator::transition`] leaves it). Each action is clipped to the range the model
    /// was trained on (`drivesim.actions`), so it passes [`Model::check_actions`]. A model
    /// without a policy is [`Error::NoPolicy`].
    ///
    /// ```
    /// let model = drivesim::Model::load("weights/default.safetensors")?;
    /// let mut sim = drivesim::Simulator::new(&model)?;
    /// let (z, h, mut action) = (vec![0.0; 128], vec![0.0; 256], [0.0; 2]);
    /// sim.act(&z, &h, &mut action)?; // (speed to drive at, steering)
    /// model.check_actions(&action)?;
    /// # Ok::<(), drivesim::Error>(())
    /// ```
    pub fn act(&mut self, z: &[f32], h: &[f32], actions: &mut [f32]) -> Result<()> {
        self.run_head(HeadKind::Policy, z, h, actions)
    }

    /// The reward head's reading of states a decision led to (`reward.*` tensors): for each
    /// item, `(reward, off-road chance)`, the env's reward expected for the decision and the
    /// chance that the car is off the road (clamped to [0, 1]). `z` is the code after the step
    /// (the next frame's, or the step's prediction) and `h` the hidden state the step left.
    /// A model without the head is [`Error::NoHead`].
    pub fn reward(&mut self, z: &[f32], h: &[f32], out: &mut [f32]) -> Result<()> {
        self.run_head(HeadKind::Reward, z, h, out)
    }

    /// The value head's discounted return from each state `[z | h]` (`value.*` tensors; the
    /// discount is [`Model::discount`]): one value per item. A model without the head is
    /// [`Error::NoHead`].
    pub fn value(&mut self, z: &[f32], h: &[f32], out: &mut [f32]) -> Result<()> {
        self.run_head(HeadKind::Value, z, h, out)
    }

    /// The pace head's speed for each state `[z | h]` (`pace.*` tensors): the speed a faster
    /// driver would drive at from the frame encoded as `z` with the drive's hidden state `h`
    /// (the same state [`Simulator::act`] reads), in the model's speed units, clamped to at
    /// least 0 and not to the policy's trained range. The cloned driver drives at it where its
    /// own target speed is at the top of that range (`python/drivesim/carracing/cloned.py`).
    /// A model without the head is [`Error::NoHead`].
    ///
    /// ```
    /// let model = drivesim::Model::load("weights/default.safetensors")?;
    /// let mut sim = drivesim::Simulator::new(&model)?;
    /// let (z, h, mut speed) = (vec![0.0; 128], vec![0.0; 256], [0.0]);
    /// sim.pace(&z, &h, &mut speed)?;
    /// assert!(speed[0] >= 0.0);
    /// # Ok::<(), drivesim::Error>(())
    /// ```
    pub fn pace(&mut self, z: &[f32], h: &[f32], out: &mut [f32]) -> Result<()> {
        self.run_head(HeadKind::Pace, z, h, out)
    }

    /// The checks and the run of [`Simulator::act`], [`Simulator::reward`],
    /// [`Simulator::value`] and [`Simulator::pace`].
    fn run_head(&mut self, kind: HeadKind, z: &[f32], h: &[f32], out: &mut [f32]) -> Result<()> {
        let model = self.model.borrow();
        let c = *model.config();
        let head = head_of(model, kind)?;
        let n = self.batch_of("z", z, c.z_dim)?;
        expect_len("h", h, n * c.hidden_dim)?;
        expect_len(output_name(kind), out, n * kind.outputs(&c))?;
        expect_finite("z", z)?;
        expect_finite("h", h)?;
        let exec = Exec {
            isa: self.isa,
            pool: self.pool.as_ref(),
        };
        let inputs = &mut self.transition.concat()[..n * (c.z_dim + c.hidden_dim)];
        gather(&c, z, h, inputs);
        head.run(exec, inputs, &mut self.head_hidden[..n * head.width()], out);
        expect_finite_output(output_name(kind), out)?;
        bound(model, kind, out);
        Ok(())
    }
}

/// The model's head of `kind`, or the error that says it has none.
pub(super) fn head_of(model: &Model, kind: HeadKind) -> Result<&Head> {
    model.head(kind).ok_or(match kind {
        HeadKind::Policy => Error::NoPolicy,
        _ => Error::NoHead { head: kind.name() },
    })
}

/// Each item's `[z | h]` into `inputs`, the heads' input rows.
pub(super) fn gather(c: &Config, z: &[f32], h: &[f32], inputs: &mut [f32]) {
    let rows = inputs.chunks_exact_mut(c.z_dim + c.hidden_dim);
    for (row, (z, h)) in rows.zip(z.chunks_exact(c.z_dim).zip(h.chunks_exact(c.hidden_dim))) {
        row[..c.z_dim].copy_from_slice(z);
        row[c.z_dim..].copy_from_slice(h);
    }
}

/// What a head's outputs are called in an error.
pub(super) fn output_name(kind: HeadKind) -> &'static str {
    match kind {
        HeadKind::Policy => "actions",
        HeadKind::Reward => "rewards",
        HeadKind::Value => "values",
        HeadKind::Pace => "speeds",
    }
}

/// A head's outputs brought into their range: the policy's actions into the model's trained
/// ranges, the reward head's off-road chances into [0, 1], the pace's speeds to at least 0.
pub(super) fn bound(model: &Model, kind: HeadKind, out: &mut [f32]) {
    match (kind, model.actions()) {
        (HeadKind::Policy, Some(specs)) => {
            for item in out.chunks_exact_mut(specs.len()) {
                for (value, spec) in item.iter_mut().zip(specs) {
                    *value = value.clamp(spec.min, spec.max);
                }
            }
        }
        (HeadKind::Reward, _) => out.iter_mut().skip(1).step_by(2).for_each(|p| *p = p.clamp(0.0, 1.0)),
        (HeadKind::Pace, _) => out.iter_mut().for_each(|v| *v = v.max(0.0)),
        _ => {}
    }
}
