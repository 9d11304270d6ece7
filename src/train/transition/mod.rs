//! Training the transition model, `h' = tanh(W h + V z + U c + b)`, `z' = A h' + a`, as
//! `weights/drivesim_reference/train.py` does: windows of codes, the first inputs teacher-forced and the later ones
//! the model's own previous prediction, mean squared error over every prediction,
//! back-propagation through time, gradient-norm clipping and Adam.
//!
//! Everything lives in one arena ([`TransitionPlan`]): the master weights in the kernels'
//! packed layout (so that the forward pass runs on them directly and the optimiser updates them
//! in place), their gradients and Adam moments in the same layout, the transposed packings the
//! backward pass multiplies by, and the activations saved for it.
//!
//! The files: `plan` (the [`TransitionPlan`] and the arena's buffers), `settings`
//! ([`TransitionSettings`]), `trainer` (the public API of [`TransitionTrainer`]), `bptt` (the
//! forward pass over windows and back-propagation through time), `threads` (how the threads share
//! a step), `state` (its state as bytes, for checkpoints) and `work` (the count of a step's work
//! per thread).

mod bptt;
mod plan;
mod settings;
mod spread;
mod state;
mod threads;
mod trainer;
mod work;

pub use plan::TransitionPlan;
pub use settings::TransitionSettings;
pub use trainer::TransitionTrainer;
