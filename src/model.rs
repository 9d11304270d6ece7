//! A loaded model: the three networks with weights packed for the kernels.

use crate::actions::ActionSpec;
use crate::encoder::Encoder;
use crate::generator::Generator;
use crate::heads::{Head, HeadKind};
use crate::metadata::Described;
use crate::transition::Transition;
use crate::weights::{RandomSource, SafetensorsSource, TensorSource, WeightDtype};
use crate::{Config, Result};
use alloc::vec::Vec;

/// The encoder, transition and generator of "Learning a Driving Simulator", ready to run.
///
/// Loading validates every tensor against the config (shape, one dtype for the file, no
/// tensor the config does not use (but the optional heads', `policy.*`, `reward.*`, `value.*`), every value finite, BatchNorm variances non-negative), folds BatchNorm (PyTorch eval semantics:
/// running statistics, eps 1e-5) into the neighbouring layers and repacks weights into the
/// kernels' layouts, once. A `Model` is immutable; run it through a [`crate::Simulator`].
pub struct Model {
    config: Config,
    actions: Option<Vec<ActionSpec>>,
    frame_hz: Option<f32>,
    discount: Option<f32>,
    pub(crate) encoder: Encoder,
    pub(crate) generator: Generator,
    pub(crate) transition: Transition,
    /// The cloned driver, where the file has one (`policy.*` tensors).
    pub(crate) policy: Option<Head>,
    /// The reward and value heads, where the file has them (`reward.*`, `value.*`).
    pub(crate) reward: Option<Head>,
    pub(crate) value: Option<Head>,
    /// The pace head, where the file has it (`pace.*`).
    pub(crate) pace: Option<Head>,
}

impl Model {
    /// Reads a drivesim safetensors weight file (format: `weights/README.md`).
    ///
    /// ```
    /// // The trained default model of the repository (13.8 MiB, f16).
    /// let model = drivesim::Model::load("weights/default.safetensors")?;
    /// assert_eq!((model.config().height, model.config().width, model.config().z_dim), (80, 160, 128));
    /// # Ok::<(), drivesim::Error>(())
    /// ```
    #[cfg(feature = "std")]
    pub fn load(path: impl AsRef<std::path::Path>) -> Result<Model> {
        let path = path.as_ref();
        let bytes = std::fs::read(path).map_err(|source| crate::Error::Io {
            path: path.display().to_string(),
            source,
        })?;
        Model::from_bytes(&bytes)
    }

    /// Builds a model from the bytes of a weight file. The bytes need no particular alignment,
    /// so `include_bytes!` works on targets without a file system.
    pub fn from_bytes(bytes: &[u8]) -> Result<Model> {
        let (config, described, mut src) = SafetensorsSource::parse(bytes)?;
        Model::build(config, described, &mut src)
    }

    /// A model with seeded pseudo-random weights (for tests and benchmarks): the same seed and
    /// config give the same model on every platform.
    pub fn random(config: &Config, seed: u64, dtype: WeightDtype) -> Result<Model> {
        config.validate()?;
        Model::build(*config, Described::default(), &mut RandomSource::new(seed, dtype))
    }

    fn build(config: Config, described: Described, src: &mut dyn TensorSource) -> Result<Model> {
        let model = Model {
            actions: described.actions,
            frame_hz: described.frame_hz,
            discount: described.discount,
            encoder: Encoder::load(&config, src)?,
            generator: Generator::load(&config, src)?,
            transition: Transition::load(&config, src)?,
            policy: Head::load(&config, src, HeadKind::Policy)?,
            reward: Head::load(&config, src, HeadKind::Reward)?,
            value: Head::load(&config, src, HeadKind::Value)?,
            pace: Head::load(&config, src, HeadKind::Pace)?,
            config,
        };
        src.finish()?;
        Ok(model)
    }

    /// What each action input means and the range it was trained on, from the file's
    /// `drivesim.actions` metadata; `None` for files without it (and random models).
    pub fn actions(&self) -> Option<&[ActionSpec]> {
        self.actions.as_deref()
    }

    /// The frame rate the model was trained at, in frames per second (one transition step is
    /// `1 / frame_hz` seconds), from the file's `drivesim.frame_hz` metadata; `None` for files
    /// without it (and random models).
    ///
    /// ```
    /// let model = drivesim::Model::load("weights/default.safetensors")?;
    /// assert_eq!(model.frame_hz(), Some(12.5)); // CarRacing's 50 Hz physics, every 4th step
    /// # Ok::<(), drivesim::Error>(())
    /// ```
    pub fn frame_hz(&self) -> Option<f32> {
        self.frame_hz
    }

    /// Checks a plan of actions (`action_dim` values per step) against the ranges the model
    /// was trained on: the first value outside is [`crate::Error::ActionRange`], with the
    /// numbers. A model without action metadata accepts every plan.
    ///
    /// ```
    /// let model = drivesim::Model::load("weights/default.safetensors")?;
    /// if let Err(e) = model.check_actions(&[0.5, 0.0]) {
    ///     eprintln!("warning: {e}"); // e.g. a speed far below anything the model saw
    /// }
    /// # Ok::<(), drivesim::Error>(())
    /// ```
    pub fn check_actions(&self, actions: &[f32]) -> Result<()> {
        match &self.actions {
            Some(specs) => crate::actions::check_plan(specs, actions),
            None => Ok(()),
        }
    }

    /// Units of the hidden layer of the model's policy (the cloned driver that
    /// [`crate::Simulator::act`] runs), or `None` where the file has no `policy.*` tensors.
    ///
    /// ```
    /// let model = drivesim::Model::load("weights/default.safetensors")?;
    /// assert_eq!(model.policy_width(), Some(64));
    /// # Ok::<(), drivesim::Error>(())
    /// ```
    pub fn policy_width(&self) -> Option<usize> {
        self.head_width(HeadKind::Policy)
    }

    /// Units of the hidden layer of one of the model's heads, or `None` where the file has no
    /// tensors under its prefix.
    ///
    /// ```
    /// use drivesim::HeadKind;
    /// let model = drivesim::Model::load("weights/default.safetensors")?;
    /// assert_eq!(model.head_width(HeadKind::Policy), model.policy_width());
    /// # Ok::<(), drivesim::Error>(())
    /// ```
    pub fn head_width(&self, kind: HeadKind) -> Option<usize> {
        self.head(kind).map(Head::width)
    }

    pub(crate) fn head(&self, kind: HeadKind) -> Option<&Head> {
        match kind {
            HeadKind::Policy => self.policy.as_ref(),
            HeadKind::Reward => self.reward.as_ref(),
            HeadKind::Value => self.value.as_ref(),
            HeadKind::Pace => self.pace.as_ref(),
        }
    }

    /// The discount per decision (transition step) that the value head's returns were
    /// discounted with, from the file's `drivesim.discount` metadata; `None` without it.
    pub fn discount(&self) -> Option<f32> {
        self.discount
    }

    /// Whether the transition can sample its codes, so that a simulator can sample futures
    /// ([`crate::Simulator::set_sampling`]): it predicts their spread (`transition.S`,
    /// `transition.s`), or it has the texture net (`transition.texture.*`, [`Model::texture_width`]).
    pub fn samples(&self) -> bool {
        self.transition.samples()
    }

    /// The width of the transition's texture net (`transition.texture.*`), where it has one: a
    /// sampler trained adversarially so that sampled futures keep the road's kerbs and grass
    /// patches, used by sampling in place of the spread head (docs/history/next_second.md).
    pub fn texture_width(&self) -> Option<usize> {
        self.transition.texture_width()
    }

    /// Whether the sampled noise is correlated across the code's dimensions (`transition.L`, fitted
    /// by `train::fit_noise_factor` with the `train` feature); without it each dimension's noise is
    /// independent.
    pub fn samples_correlated(&self) -> bool {
        self.transition.correlates()
    }

    /// The architecture the weights were built for.
    pub fn config(&self) -> &Config {
        &self.config
    }
}

impl core::fmt::Debug for Model {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("Model")
            .field("config", &self.config)
            .field("actions", &self.actions)
            .field("folds_fed_back_steps", &self.transition.folds())
            .field("policy_width", &self.policy_width())
            .field("reward_width", &self.head_width(HeadKind::Reward))
            .field("value_width", &self.head_width(HeadKind::Value))
            .field("pace_width", &self.head_width(HeadKind::Pace))
            .finish_non_exhaustive()
    }
}
