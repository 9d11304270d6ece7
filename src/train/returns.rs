//! The targets a value head learns: λ-returns (Sutton & Barto, 12.1), TD(λ) in its forward view.

use crate::{Error, Result};

/// The λ-returns of one drive, into `out`: for decision `t` of `T`,
/// `G_t = r_t + γ ((1 - λ) v_{t+1} + λ G_{t+1})` with `G_T = v_T`, where `rewards` holds
/// `r_0 .. r_{T-1}` and `next_values` the value of the state each decision led to,
/// `v_1 .. v_T` (`v_T` 0 where the drive ended for good, the value head's estimate where it
/// was only cut off). λ = 0 is the one-step TD target `r_t + γ v_{t+1}`; λ = 1 the discounted
/// sum of the rewards to the end, plus `γ^(T-t) v_T`.
///
/// `discount` (γ) and `lambda` from 0 to 1 ([`Error::Setting`] otherwise), the slices of one
/// length ([`Error::BufferLength`]) and finite ([`Error::NonFinite`]).
///
/// ```
/// use drivesim::train::lambda_returns;
/// let mut g = [0.0; 3];
/// lambda_returns(&[1.0, 1.0, 1.0], &[0.0, 0.0, 0.0], 0.5, 1.0, &mut g)?;
/// assert_eq!(g, [1.75, 1.5, 1.0]);
/// # Ok::<(), drivesim::Error>(())
/// ```
pub fn lambda_returns(rewards: &[f32], next_values: &[f32], discount: f32, lambda: f32, out: &mut [f32]) -> Result<()> {
    for (name, value) in [("discount", discount), ("lambda", lambda)] {
        if !(0.0..=1.0).contains(&value) {
            return Err(Error::Setting {
                name,
                expected: "from 0 to 1",
                value,
            });
        }
    }
    crate::error::expect_len("next_values", next_values, rewards.len())?;
    crate::error::expect_len("out", out, rewards.len())?;
    crate::error::expect_finite("rewards", rewards)?;
    crate::error::expect_finite("next_values", next_values)?;
    let mut next = match next_values.last() {
        Some(&v) => v,
        None => return Ok(()),
    };
    for t in (0..rewards.len()).rev() {
        let g = rewards[t] + discount * ((1.0 - lambda) * next_values[t] + lambda * next);
        out[t] = g;
        next = g;
    }
    crate::error::expect_finite_output("returns", out)
}
