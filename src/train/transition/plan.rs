//! The trainer's arena, planned before anything is allocated: its buffers in order, the sizes
//! they follow from ([`Dims`]) and [`TransitionPlan`].

use super::threads::partials_len;
use crate::train::arena::{bytes_of, total};
use crate::{Config, Error, Result};
use drivesim_kernels::Matrix;

/// The arena's buffers, in order.
const BUFFERS: [&str; 16] = [
    "weights",
    "gradients",
    "Adam first moments",
    "Adam second moments",
    "[Aᵀ | Wᵀ] (hidden-state gradient)",
    "[Vᵀ ; Uᵀ] (input gradient)",
    "saved inputs [h | z | c]",
    "saved hidden states",
    "saved predictions",
    "pre-activation gradients",
    "prediction gradients",
    "input gradients",
    "gathered [dz' | dpre]",
    "zero bias",
    "action normalisation",
    "partial weight gradients",
];

/// The memory of a [`TransitionTrainer`](super::TransitionTrainer), computed from the config,
/// the batch and the window length before anything is allocated. Threads need none of their
/// own: they share each product by rows and items, and each weight gradient by rows and blocks
/// of items summed apart ("partial weight gradients", for 256 windows' steps and more).
///
/// ```
/// use drivesim::train::TransitionPlan;
/// use drivesim::Config;
///
/// let plan = TransitionPlan::new(&Config::COMMA, 16, 15)?;
/// for (buffer, bytes) in plan.buffers() {
///     println!("{buffer:>36}: {bytes} bytes");
/// }
/// assert!(plan.bytes() < 24 << 20);
/// assert!(TransitionPlan::new(&Config::COMMA, usize::MAX, 15).is_err());
/// # Ok::<(), drivesim::Error>(())
/// ```
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TransitionPlan {
    pub(super) dims: Dims,
    pub(super) lens: [usize; BUFFERS.len()],
    bytes: usize,
}

/// The sizes every buffer follows from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct Dims {
    pub(super) hidden: usize,
    pub(super) z: usize,
    pub(super) actions: usize,
    /// Most windows per step.
    pub(super) batch: usize,
    /// Codes per window (`T`): `T - 1` predictions.
    pub(super) window: usize,
    /// Whether the transition has the spread head `S`, `s` (sampled futures).
    pub(super) spread: bool,
}

impl Dims {
    /// Columns of `[W | V | U]`.
    pub(super) fn cols(&self) -> usize {
        self.hidden + self.z + self.actions
    }

    /// Predictions per window.
    pub(super) fn steps(&self) -> usize {
        self.window - 1
    }

    /// Floats of `[W | V | U]` packed, `b`, `A` packed, `a`, and the spread head's `S`
    /// packed and `s` (none without it), in that order.
    pub(super) fn params(&self) -> [usize; 6] {
        let (h, z) = (self.hidden, self.z);
        let spread = if self.spread {
            [Matrix::packed_len(z, h), z]
        } else {
            [0, 0]
        };
        [
            Matrix::packed_len(h, self.cols()),
            h,
            Matrix::packed_len(z, h),
            z,
            spread[0],
            spread[1],
        ]
    }

    /// Floats of the parameters before the spread head's: those the clipping norm covers.
    pub(super) fn clipped(&self) -> usize {
        self.params()[..4].iter().sum()
    }
}

const WHAT: &str = "the transition trainer's arena";

fn mul(a: usize, b: usize) -> Result<usize> {
    a.checked_mul(b).ok_or(Error::OutOfMemory {
        what: WHAT,
        bytes: None,
    })
}

impl TransitionPlan {
    /// The arena of a trainer for `config`'s transition taking up to `batch` windows of
    /// `window` codes (at least 2: one input, one target) per step.
    pub fn new(config: &Config, batch: usize, window: usize) -> Result<TransitionPlan> {
        config.validate()?;
        if window < 2 {
            return Err(Error::Config {
                field: "window",
                expected: "at least 2 codes",
                found: window,
            });
        }
        if batch == 0 {
            return Err(Error::Config {
                field: "batch",
                expected: "at least 1 window",
                found: 0,
            });
        }
        TransitionPlan::of(Dims {
            hidden: config.hidden_dim,
            z: config.z_dim,
            actions: config.action_dim,
            batch,
            window,
            spread: false,
        })
    }

    /// The plan with room for the spread head (`transition.S`, `transition.s`): the log standard
    /// deviation of each predicted code's dimension, which sampled futures draw from
    /// ([`crate::Simulator::set_sampling`]). A model with a spread head trains only in such a
    /// plan; one without starts a new head (zeros: a unit spread).
    pub fn with_spread(&self) -> Result<TransitionPlan> {
        TransitionPlan::of(Dims {
            spread: true,
            ..self.dims
        })
    }

    /// [`TransitionPlan::new`] for `model`'s config, with room for its spread head where it
    /// has one ([`crate::Model::samples`]).
    pub fn for_model(model: &crate::Model, batch: usize, window: usize) -> Result<TransitionPlan> {
        let plan = TransitionPlan::new(model.config(), batch, window)?;
        match model.samples() {
            true => plan.with_spread(),
            false => Ok(plan),
        }
    }

    /// Whether the plan has room for the spread head ([`TransitionPlan::with_spread`]).
    pub fn spread(&self) -> bool {
        self.dims.spread
    }

    /// The buffers of checked sizes.
    fn of(dims: Dims) -> Result<TransitionPlan> {
        let (h, z, a, batch) = (dims.hidden, dims.z, dims.actions, dims.batch);
        let params = total(&dims.params(), WHAT)?;
        let items = mul(dims.steps(), batch)?;
        let lens = [
            params,
            params,
            params,
            params,
            Matrix::packed_len(h, z + h),
            Matrix::packed_len(z + a, h),
            mul(items, dims.cols())?,
            mul(items, h)?,
            mul(items, z)?,
            mul(items, h)?,
            mul(items, z)?,
            mul(items, z + a)?,
            mul(batch, z + h)?,
            h.max(z + a),
            2 * a,
            // The weight gradients' blocks, one gradient at a time (the spread head's as A's).
            partials_len(h, dims.cols(), items).max(partials_len(z, h, items)),
        ];
        let bytes = bytes_of(total(&lens, WHAT)?, WHAT)?;
        Ok(TransitionPlan { dims, lens, bytes })
    }

    /// Bytes of the whole arena.
    pub fn bytes(&self) -> usize {
        self.bytes
    }

    /// Each buffer of the arena with its bytes, in the arena's order.
    pub fn buffers(&self) -> impl Iterator<Item = (&'static str, usize)> + '_ {
        BUFFERS.iter().zip(self.lens).map(|(&name, len)| (name, len * 4))
    }

    /// The most windows one step takes.
    pub fn batch(&self) -> usize {
        self.dims.batch
    }

    /// Codes per window.
    pub fn window(&self) -> usize {
        self.dims.window
    }

    pub(super) fn floats(&self) -> usize {
        self.bytes / 4
    }
}
