//! The optional heads of a weight file: small networks that read what the models know of the
//! road at a moment, the code `z` and the transition's hidden state `h`, as `[z | h]` (World
//! Models' controller reads the same two), through one tanh layer of `width` units.
//!
//! - The **policy** (`policy.*`): the cloned driver, the action a driver would take at a frame
//!   ([`crate::Simulator::act`]; trainer [`crate::train::HeadTrainer`] with [`HeadKind::Policy`]).
//!   `h` is the state after the transition was fed the drive's codes and actions up to the
//!   frame before, from zeros at its first: what [`crate::Simulator::transition`] gives when
//!   stepped along a drive.
//! - The **reward** head (`reward.*`): read after a step, from the state the step reached (the
//!   next frame's code and the hidden state the step left, which has seen the action), the
//!   env's reward for that decision and the chance that the car is off the road there.
//! - The **value** head (`value.*`): the discounted return from a state under the driving
//!   policy, the discount per decision in the file's `drivesim.discount` metadata.
//! - The **pace** head (`pace.*`): the speed a faster driver would drive at from the state (the
//!   expert at racing pace, learnt by `train policy --pace` from DAgger's labels), read where
//!   the policy is at the top of its trained speed range ([`crate::Simulator::pace`]).
//!
//! The planner reads the reward and value heads in its rollouts ([`crate::Simulator::rollout_candidates_scored`]).

use crate::layers::DenseLayer;
use crate::pool::Exec;
use crate::weights::{Init, TensorSource};
use crate::{Config, Error, Result};
use alloc::format;
use drivesim_kernels::Activation;

/// Which head: its tensors' prefix and its outputs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum HeadKind {
    /// The cloned driver: `action_dim` outputs, the action in the model's units.
    Policy,
    /// Two outputs: the env's reward for the decision that led to the state, and the chance
    /// that the car is off the road there (trained on 0 or 1; read clamped to [0, 1]).
    Reward,
    /// One output: the discounted return from the state.
    Value,
    /// One output: the speed to drive at, at racing pace (the model's speed units, read clamped
    /// to at least 0).
    Pace,
}

impl HeadKind {
    /// Every head, in the order a weight file is read.
    pub const ALL: [HeadKind; 4] = [HeadKind::Policy, HeadKind::Reward, HeadKind::Value, HeadKind::Pace];

    /// The head's name: `policy`, `reward`, `value` or `pace`.
    pub fn name(self) -> &'static str {
        match self {
            HeadKind::Policy => "policy",
            HeadKind::Reward => "reward",
            HeadKind::Value => "value",
            HeadKind::Pace => "pace",
        }
    }

    /// The prefix of its tensors in a weight file (`policy.`, `reward.`, `value.`, `pace.`).
    pub fn prefix(self) -> &'static str {
        match self {
            HeadKind::Policy => "policy.",
            HeadKind::Reward => "reward.",
            HeadKind::Value => "value.",
            HeadKind::Pace => "pace.",
        }
    }

    /// Its outputs per item.
    pub fn outputs(self, config: &Config) -> usize {
        match self {
            HeadKind::Policy => config.action_dim,
            HeadKind::Reward => 2,
            HeadKind::Value | HeadKind::Pace => 1,
        }
    }
}

/// A head's two layers, packed for the kernels.
pub(crate) struct Head {
    hidden: DenseLayer,
    output: DenseLayer,
}

impl Head {
    /// Reads `{prefix}hidden.{weight,bias}` (`[width, z_dim + hidden_dim]`, `[width]`) and
    /// `{prefix}output.{weight,bias}` (`[outputs, width]`, `[outputs]`), where the source has
    /// any tensor under the head's prefix; `None` where it has none. `width` is the hidden
    /// layer's bias length, 1 to `hidden_dim` (heads run in the simulator's planned buffers).
    pub fn load(config: &Config, src: &mut dyn TensorSource, kind: HeadKind) -> Result<Option<Head>> {
        Head::load_at(config, src, kind.prefix(), kind.outputs(config))
    }

    /// [`Head::load`] of the two layers under `prefix` with `outputs` outputs: also the
    /// transition's texture net ([`crate::texture`]), which has the heads' shape.
    pub(crate) fn load_at(
        config: &Config,
        src: &mut dyn TensorSource,
        prefix: &str,
        outputs: usize,
    ) -> Result<Option<Head>> {
        if !src.contains(prefix) {
            return Ok(None);
        }
        let bias = format!("{prefix}hidden.bias");
        let width = match src.shape(&bias).as_deref() {
            Some(&[width]) => width,
            Some(found) => {
                return Err(Error::Shape {
                    name: bias,
                    expected: alloc::vec![config.hidden_dim],
                    found: found.to_vec(),
                })
            }
            None => return Err(Error::MissingTensor { name: bias }),
        };
        if !(1..=config.hidden_dim).contains(&width) {
            return Err(Error::Config {
                field: "head width (a head's hidden.bias length)",
                expected: "1 to hidden_dim",
                found: width,
            });
        }
        Head::read_at(config, src, prefix, outputs, width).map(Some)
    }

    /// The layers of width `width` from `src` (a file's, or a random draw for a trainer's start).
    #[cfg(feature = "train")]
    pub(crate) fn read(config: &Config, src: &mut dyn TensorSource, kind: HeadKind, width: usize) -> Result<Head> {
        Head::read_at(config, src, kind.prefix(), kind.outputs(config), width)
    }

    /// [`Head::read`] of the layers under `prefix` `p` with `outputs` outputs.
    pub(crate) fn read_at(
        config: &Config,
        src: &mut dyn TensorSource,
        p: &str,
        outputs: usize,
        width: usize,
    ) -> Result<Head> {
        let cols = config.z_dim + config.hidden_dim;
        let w1 = src.tensor(&format!("{p}hidden.weight"), &[width, cols], Init::FanIn(cols))?;
        let b1 = src.f32(&format!("{p}hidden.bias"), &[width], Init::FanIn(cols))?;
        let w2 = src.tensor(&format!("{p}output.weight"), &[outputs, width], Init::FanIn(width))?;
        let b2 = src.f32(&format!("{p}output.bias"), &[outputs], Init::FanIn(width))?;
        Ok(Head {
            hidden: DenseLayer::new(w1, b1, width, cols, Activation::Tanh),
            output: DenseLayer::new(w2, b2, outputs, width, Activation::Identity),
        })
    }

    /// Units of the hidden layer.
    pub fn width(&self) -> usize {
        self.hidden.rows
    }

    /// The two layers (a trainer's start).
    #[cfg(feature = "train")]
    pub(crate) fn layers(&self) -> (&DenseLayer, &DenseLayer) {
        (&self.hidden, &self.output)
    }

    /// The outputs of a batch: `inputs` holds each item's `[z | h]`, `hidden` room for
    /// `width` values per item.
    pub fn run(&self, exec: Exec<'_>, inputs: &[f32], hidden: &mut [f32], outputs: &mut [f32]) {
        self.hidden.run(exec, inputs, hidden);
        self.output.run(exec, hidden, outputs);
    }
}
