//! What a weight file says beyond its tensors and config, in its metadata: what the actions
//! mean (`drivesim.actions`), the frames' rate (`drivesim.frame_hz`) and the value head's
//! discount (`drivesim.discount`); read at load, written by the trainers.

use crate::actions::{ActionSpec, ACTIONS_KEY};
use crate::{Error, Result};
use alloc::format;
use alloc::vec::Vec;

/// The metadata key of the frame rate a model was trained at: a decimal number of frames per
/// second (`"12.5"`), as the episodes files' `frame_hz`.
pub(crate) const FRAME_HZ_KEY: &str = "drivesim.frame_hz";

/// The metadata key of the discount per decision of a value head's returns: a decimal number
/// above 0 and below 1 (`"0.98"`).
pub(crate) const DISCOUNT_KEY: &str = "drivesim.discount";

#[cfg(feature = "train")]
/// What a trainer writes about its training data into a weight file's metadata
/// ([`crate::train::TransitionTrainer::weight_file`], [`crate::train::VaeGanTrainer::weight_file`]); what is `None` stays
/// as the original file has it.
#[derive(Clone, Copy, Debug, Default)]
pub struct TrainedOn<'a> {
    /// What the actions mean and their range (`drivesim.actions`).
    pub actions: Option<&'a [ActionSpec]>,
    /// The frames' rate (`drivesim.frame_hz`), e.g. [`crate::Episodes::frame_hz`].
    pub frame_hz: Option<f32>,
    /// The value head's discount per decision (`drivesim.discount`).
    pub discount: Option<f32>,
}

/// What a weight file says about its inputs beyond the config: what the actions mean
/// (`drivesim.actions`), how far apart its frames are (`drivesim.frame_hz`) and the value
/// head's discount (`drivesim.discount`).
#[derive(Default)]
pub(crate) struct Described {
    pub actions: Option<Vec<ActionSpec>>,
    pub frame_hz: Option<f32>,
    pub discount: Option<f32>,
}

/// A discount in metadata: a number above 0 and below 1.
pub(crate) fn parse_discount(text: &str) -> Result<f32> {
    parse_number(
        DISCOUNT_KEY,
        text,
        |d| d > 0.0 && d < 1.0,
        "a number above 0 and below 1",
    )
}

/// A frame rate in metadata (`key`: a weight file's `drivesim.frame_hz`, an episodes file's
/// `frame_hz`): a finite number above zero.
pub(crate) fn parse_frame_hz(key: &str, text: &str) -> Result<f32> {
    parse_number(
        key,
        text,
        |hz| hz.is_finite() && hz > 0.0,
        "frames per second above zero",
    )
}

/// A number in metadata under `key` that `valid` accepts, else what was `expected`.
fn parse_number(key: &str, text: &str, valid: fn(f32) -> bool, expected: &str) -> Result<f32> {
    let number = text.trim().parse::<f32>().ok().filter(|&v| valid(v));
    number.ok_or_else(|| Error::Metadata {
        reason: format!("`{key}`: expected {expected}, found {text:?}"),
    })
}

impl Described {
    /// What the metadata (`key` gives a key's text) says, each value checked.
    pub(crate) fn read<'a>(
        key: &dyn Fn(&str) -> Option<&'a alloc::string::String>,
        action_dim: usize,
    ) -> Result<Described> {
        Ok(Described {
            actions: key(ACTIONS_KEY)
                .map(|json| ActionSpec::parse_all(json, action_dim))
                .transpose()?,
            frame_hz: key(FRAME_HZ_KEY)
                .map(|text| parse_frame_hz(FRAME_HZ_KEY, text))
                .transpose()?,
            discount: key(DISCOUNT_KEY).map(|text| parse_discount(text)).transpose()?,
        })
    }
}

/// What a trainer says of its training (`trained_on`) into a file's `metadata`, each value
/// checked to read back.
#[cfg(all(feature = "std", feature = "train"))]
pub(crate) fn write(
    trained_on: &TrainedOn<'_>,
    action_dim: usize,
    metadata: &mut std::collections::HashMap<alloc::string::String, alloc::string::String>,
) -> Result<()> {
    use alloc::string::ToString;
    if let Some(actions) = trained_on.actions {
        let json = ActionSpec::to_json(actions);
        ActionSpec::parse_all(&json, action_dim)?; // what is written must read back
        metadata.insert(ACTIONS_KEY.to_string(), json);
    }
    if let Some(hz) = trained_on.frame_hz {
        let text = format!("{hz}");
        parse_frame_hz(FRAME_HZ_KEY, &text)?;
        metadata.insert(FRAME_HZ_KEY.to_string(), text);
    }
    if let Some(discount) = trained_on.discount {
        let text = format!("{discount}");
        parse_discount(&text)?;
        metadata.insert(DISCOUNT_KEY.to_string(), text);
    }
    Ok(())
}
