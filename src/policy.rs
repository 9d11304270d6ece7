//! The cloned driver: an optional policy network in the weight file (`policy.*` tensors), from
//! what the models know of the road now to the action a driver would take.
//!
//! It reads the encoder's code of the current frame and the transition's hidden state, `[z | h]`
//! (World Models' controller reads the same two), through one tanh layer of `width` units to
//! the `action_dim` values of the action, in the units of the model's actions (for CarRacing,
//! the speed to drive at and the steering). `h` is the state after the transition has been fed
//! the episode's codes and actions up to the previous frame, from zeros at its first: what
//! [`crate::Simulator::transition`] gives when stepped along a drive. The trainer is
//! [`crate::train::PolicyTrainer`].

use crate::layers::DenseLayer;
use crate::pool::Exec;
use crate::weights::{Init, TensorSource};
use crate::{Config, Error, Result};
use drivesim_kernels::Activation;

/// The prefix of the policy's tensors in a weight file.
pub(crate) const POLICY_PREFIX: &str = "policy.";

/// The policy's two layers, packed for the kernels.
pub(crate) struct Policy {
    hidden: DenseLayer,
    output: DenseLayer,
}

impl Policy {
    /// Reads `policy.hidden.{weight,bias}` (`[width, z_dim + hidden_dim]`, `[width]`) and
    /// `policy.output.{weight,bias}` (`[action_dim, width]`, `[action_dim]`), where the source
    /// has any `policy.` tensor; `None` where it has none. `width` is the hidden layer's bias
    /// length, 1 to `hidden_dim` (the policy runs in the simulator's rollout buffers).
    pub fn load(config: &Config, src: &mut dyn TensorSource) -> Result<Option<Policy>> {
        if !src.contains(POLICY_PREFIX) {
            return Ok(None);
        }
        let width = match src.shape("policy.hidden.bias").as_deref() {
            Some(&[width]) => width,
            Some(found) => {
                return Err(Error::Shape {
                    name: "policy.hidden.bias".into(),
                    expected: alloc::vec![config.hidden_dim],
                    found: found.to_vec(),
                })
            }
            None => {
                return Err(Error::MissingTensor {
                    name: "policy.hidden.bias".into(),
                })
            }
        };
        if !(1..=config.hidden_dim).contains(&width) {
            return Err(Error::Config {
                field: "policy width (policy.hidden.bias's length)",
                expected: "1 to hidden_dim",
                found: width,
            });
        }
        Policy::read(config, src, width).map(Some)
    }

    /// The layers of width `width` from `src` (a file's, or a random draw for a trainer's start).
    pub(crate) fn read(config: &Config, src: &mut dyn TensorSource, width: usize) -> Result<Policy> {
        let (cols, actions) = (config.z_dim + config.hidden_dim, config.action_dim);
        let w1 = src.tensor("policy.hidden.weight", &[width, cols], Init::FanIn(cols))?;
        let b1 = src.f32("policy.hidden.bias", &[width], Init::FanIn(cols))?;
        let w2 = src.tensor("policy.output.weight", &[actions, width], Init::FanIn(width))?;
        let b2 = src.f32("policy.output.bias", &[actions], Init::FanIn(width))?;
        Ok(Policy {
            hidden: DenseLayer::new(w1, b1, width, cols, Activation::Tanh),
            output: DenseLayer::new(w2, b2, actions, width, Activation::Identity),
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

    /// The actions of a batch: `inputs` holds each item's `[z | h]`, `hidden` room for `width`
    /// values per item.
    pub fn run(&self, exec: Exec<'_>, inputs: &[f32], hidden: &mut [f32], actions: &mut [f32]) {
        self.hidden.run(exec, inputs, hidden);
        self.output.run(exec, hidden, actions);
    }
}
