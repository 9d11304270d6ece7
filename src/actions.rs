//! What a model's action inputs mean: the `drivesim.actions` metadata of a weight file (its
//! format is in `weights/README.md`). A plan outside the range the model was trained on gives a
//! broken road without any error, so the numbers travel with the weights.

use crate::{Error, Result};
use alloc::format;
use alloc::string::{String, ToString};
use alloc::vec::Vec;
use serde_json::Value;

/// One action input as the model was trained on it.
#[derive(Clone, Debug, PartialEq)]
pub struct ActionSpec {
    /// What it is, e.g. "speed".
    pub name: String,
    /// Its unit, e.g. "Box2D units/s" (CarRacing) or "m/s".
    pub unit: String,
    /// Its mean over the training data.
    pub mean: f32,
    /// Its standard deviation over the training data.
    pub std: f32,
    /// The smallest value in the training data.
    pub min: f32,
    /// The largest value in the training data.
    pub max: f32,
}

/// The metadata key.
pub const ACTIONS_KEY: &str = "drivesim.actions";

impl ActionSpec {
    /// Parses the `drivesim.actions` JSON array, which must describe `action_dim` actions.
    pub fn parse_all(json: &str, action_dim: usize) -> Result<Vec<ActionSpec>> {
        let bad = |reason: String| Error::Metadata {
            reason: format!("`{ACTIONS_KEY}`: {reason} in {json:?}"),
        };
        let value: Value = serde_json::from_str(json).map_err(|e| bad(e.to_string()))?;
        let items = value.as_array().ok_or_else(|| bad("expected a JSON array".into()))?;
        if items.len() != action_dim {
            return Err(bad(format!("{} actions for a model of {action_dim}", items.len())));
        }
        items
            .iter()
            .map(|item| {
                let text = |key: &str| {
                    item.get(key)
                        .and_then(Value::as_str)
                        .map(str::to_string)
                        .ok_or_else(|| bad(format!("no string `{key}`")))
                };
                let number = |key: &str| {
                    item.get(key)
                        .and_then(Value::as_f64)
                        .map(|v| v as f32)
                        .filter(|v| v.is_finite())
                        .ok_or_else(|| bad(format!("no finite number `{key}`")))
                };
                let spec = ActionSpec {
                    name: text("name")?,
                    unit: text("unit")?,
                    mean: number("mean")?,
                    std: number("std")?,
                    min: number("min")?,
                    max: number("max")?,
                };
                if !(spec.std > 0.0 && spec.min <= spec.max) {
                    return Err(bad(format!("`{}` needs std > 0 and min <= max", spec.name)));
                }
                Ok(spec)
            })
            .collect()
    }

    /// The JSON array [`ActionSpec::parse_all`] reads.
    pub fn to_json(specs: &[ActionSpec]) -> String {
        let items: Vec<Value> = specs
            .iter()
            .map(|s| {
                serde_json::json!({
                    "name": s.name, "unit": s.unit, "mean": s.mean, "std": s.std, "min": s.min, "max": s.max,
                })
            })
            .collect();
        Value::Array(items).to_string()
    }
}

/// Checks each action of a plan (`action_dim` values per step, back to back) against the range
/// its model was trained on: the first one outside is [`Error::ActionRange`].
pub(crate) fn check_plan(specs: &[ActionSpec], actions: &[f32]) -> Result<()> {
    for (i, value) in actions.iter().enumerate() {
        let spec = &specs[i % specs.len()];
        if !(spec.min..=spec.max).contains(value) {
            return Err(Error::ActionRange {
                index: i,
                name: spec.name.clone(),
                unit: spec.unit.clone(),
                value: *value,
                min: spec.min,
                max: spec.max,
            });
        }
    }
    Ok(())
}
