//! `drivesim.actions` and `drivesim.frame_hz`: what a weight file says its inputs mean, read,
//! checked, written back by the trainer, and absent from older files.

mod common;

use common::fixture_path;
use drivesim::{ActionSpec, Error, Model};
use safetensors::SafeTensors;
use std::collections::HashMap;

/// A fixture weight file (no action metadata) with `drivesim.actions` set to `json`.
fn with_actions(json: &str) -> Vec<u8> {
    with_metadata("drivesim.actions", json)
}

/// A fixture weight file with the metadata `key` set to `value`.
fn with_metadata(key: &str, value: &str) -> Vec<u8> {
    let bytes = std::fs::read(fixture_path("small_f32.safetensors")).unwrap();
    let (_, metadata) = SafeTensors::read_metadata(&bytes).unwrap();
    let mut metadata: HashMap<String, String> = metadata.metadata().clone().unwrap();
    metadata.insert(key.into(), value.into());
    let file = SafeTensors::deserialize(&bytes).unwrap();
    safetensors::serialize(file.tensors(), Some(metadata)).unwrap()
}

fn specs() -> Vec<ActionSpec> {
    vec![
        ActionSpec {
            name: "speed".into(),
            unit: "Box2D units/s".into(),
            mean: 24.8,
            std: 11.2,
            min: 0.0,
            max: 61.5,
        },
        ActionSpec {
            name: "steering".into(),
            unit: "command in [-1, 1]".into(),
            mean: -0.04,
            std: 0.23,
            min: -1.0,
            max: 1.0,
        },
    ]
}

#[test]
fn metadata_round_trips_and_checks_plans() {
    let model = Model::from_bytes(&with_actions(&ActionSpec::to_json(&specs()))).unwrap();
    assert_eq!(model.actions(), Some(&specs()[..]));
    model.check_actions(&[20.0, 0.3, 61.5, -1.0]).unwrap();
    match model.check_actions(&[20.0, 0.3, 0.5, 1.5]) {
        Err(Error::ActionRange {
            index: 3,
            name,
            value,
            min,
            max,
            ..
        }) => assert_eq!((name.as_str(), value, min, max), ("steering", 1.5, -1.0, 1.0)),
        other => panic!("expected ActionRange, got {other:?}"),
    }
    let message = model.check_actions(&[-3.0, 0.0]).unwrap_err().to_string();
    assert!(
        message.contains("speed") && message.contains("-3") && message.contains("61.5"),
        "{message}"
    );
}

#[test]
fn files_without_metadata_load_and_accept_every_plan() {
    let model = Model::load(fixture_path("small_f32.safetensors")).unwrap();
    assert_eq!(model.actions(), None);
    model.check_actions(&[1e6, -1e6]).unwrap();
}

#[test]
fn bad_metadata_is_an_error() {
    let one = ActionSpec::to_json(&specs()[..1]);
    let mut zero_std = specs();
    zero_std[1].std = 0.0;
    let mut inverted = specs();
    inverted[0].min = 70.0;
    for json in [
        "not json".to_string(),
        "{}".to_string(),
        one,
        ActionSpec::to_json(&zero_std),
        ActionSpec::to_json(&inverted),
        r#"[{"name": "speed"}, {"name": "steering"}]"#.to_string(),
    ] {
        assert!(
            matches!(Model::from_bytes(&with_actions(&json)), Err(Error::Metadata { .. })),
            "{json}"
        );
    }
}

#[test]
fn frame_rate_is_read_and_checked() {
    let model = Model::from_bytes(&with_metadata("drivesim.frame_hz", "12.5")).unwrap();
    assert_eq!(model.frame_hz(), Some(12.5));
    let plain = std::fs::read(fixture_path("small_f32.safetensors")).unwrap();
    assert_eq!(Model::from_bytes(&plain).unwrap().frame_hz(), None);
    for bad in ["0", "-12.5", "inf", "NaN", "twelve", ""] {
        match Model::from_bytes(&with_metadata("drivesim.frame_hz", bad)) {
            Err(Error::Metadata { reason }) => assert!(reason.contains("drivesim.frame_hz"), "{reason}"),
            other => panic!(
                "{bad:?}: expected a metadata error, got {:?}",
                other.map(|m| m.frame_hz())
            ),
        }
    }
}
