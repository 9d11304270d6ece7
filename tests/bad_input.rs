//! Bad data gets a typed error that names what was expected and what was found, never a panic.

mod common;

use common::{fixture_path, Tensor};
use drivesim::{Config, Error, Model, Plan, Simulator, WeightDtype};
use safetensors::{Dtype, SafeTensors};
use std::collections::HashMap;

fn fixture_bytes() -> Vec<u8> {
    std::fs::read(fixture_path("small_f32.safetensors")).unwrap()
}

/// The fixture's tensors and metadata, to be edited and written back.
fn fixture_parts() -> (HashMap<String, Tensor>, HashMap<String, String>) {
    let bytes = fixture_bytes();
    let (_, meta) = SafeTensors::read_metadata(&bytes).unwrap();
    let file = SafeTensors::deserialize(&bytes).unwrap();
    let tensors = file
        .tensors()
        .into_iter()
        .map(|(name, v)| {
            (
                name,
                Tensor {
                    dtype: v.dtype(),
                    shape: v.shape().to_vec(),
                    data: v.data().to_vec(),
                },
            )
        })
        .collect();
    (tensors, meta.metadata().clone().unwrap())
}

fn write(tensors: &HashMap<String, Tensor>, meta: HashMap<String, String>) -> Vec<u8> {
    safetensors::serialize(tensors.iter().map(|(k, v)| (k.clone(), v)), Some(meta)).unwrap()
}

fn load_err(bytes: &[u8]) -> Error {
    match Model::from_bytes(bytes) {
        Ok(_) => panic!("bad weights were accepted"),
        Err(e) => e,
    }
}

#[test]
fn unaligned_bytes_load() {
    let bytes = fixture_bytes();
    let mut shifted = vec![0u8; bytes.len() + 1];
    shifted[1..].copy_from_slice(&bytes);
    let model = Model::from_bytes(&shifted[1..]).unwrap();
    assert_eq!(model.config().z_dim, 20);
}

#[test]
fn truncated_and_garbage_files_are_malformed() {
    let bytes = fixture_bytes();
    // Every cut in the header, and a spread of cuts in the data.
    let header = 8 + u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let cuts = (0..header + 16)
        .chain((header..bytes.len()).step_by(4099))
        .chain([bytes.len() - 1]);
    for cut in cuts {
        let err = load_err(&bytes[..cut]);
        assert!(
            matches!(err, Error::Malformed { .. } | Error::Metadata { .. }),
            "cut at {cut}: {err}"
        );
    }
    assert!(matches!(load_err(b"not a weight file at all"), Error::Malformed { .. }));
    assert!(matches!(load_err(&[]), Error::Malformed { .. }));
}

#[test]
fn missing_or_misshapen_tensors_are_named() {
    let (mut tensors, meta) = fixture_parts();
    tensors.remove("generator.bn2.running_var");
    let err = load_err(&write(&tensors, meta.clone()));
    assert!(
        matches!(&err, Error::MissingTensor { name } if name == "generator.bn2.running_var"),
        "{err}"
    );

    let (mut tensors, _) = fixture_parts();
    tensors.get_mut("encoder.conv2.weight").unwrap().shape = vec![24, 6, 5, 10];
    let err = load_err(&write(&tensors, meta.clone()));
    match &err {
        Error::Shape { name, expected, found } => {
            assert_eq!(name, "encoder.conv2.weight");
            assert_eq!(expected, &[24, 12, 5, 5]);
            assert_eq!(found, &[24, 6, 5, 10]);
        }
        other => panic!("expected a shape error, got {other}"),
    }
    assert!(err.to_string().contains("[24, 12, 5, 5]"), "{err}");
}

#[test]
fn unsupported_dtypes_are_rejected() {
    let (mut tensors, meta) = fixture_parts();
    tensors.get_mut("transition.b").unwrap().dtype = Dtype::I32;
    let err = load_err(&write(&tensors, meta));
    assert!(
        matches!(&err, Error::Dtype { name, found } if name == "transition.b" && found == "I32"),
        "{err}"
    );
}

#[test]
fn bad_metadata_is_explained() {
    let (tensors, meta) = fixture_parts();
    let with = |json: &str| {
        let mut m = meta.clone();
        m.insert("drivesim.config".into(), json.into());
        load_err(&write(&tensors, m))
    };
    assert!(matches!(
        load_err(&write(&tensors, HashMap::new())),
        Error::Metadata { .. }
    ));
    assert!(matches!(with("{\"height\": 48"), Error::Metadata { .. }));
    assert!(matches!(with("[1, 2]"), Error::Metadata { .. }));
    let good = Config::from_json(&meta["drivesim.config"]).unwrap();
    let err = with(&good.to_json().replace("\"z_dim\":20,", ""));
    assert!(
        matches!(&err, Error::Metadata { reason } if reason.contains("z_dim")),
        "{err}"
    );
    let err = with(&good.to_json().replace("\"layers\":4", "\"layers\":-4"));
    assert!(matches!(&err, Error::Metadata { .. }), "{err}");
    for (edit, field) in [
        (("\"height\":48", "\"height\":50"), "height"),
        (("\"layers\":4", "\"layers\":3"), "layers"),
        (("\"kernel\":5", "\"kernel\":3"), "kernel"),
        (("\"z_dim\":20", "\"z_dim\":0"), "z_dim"),
        (("\"width\":112", "\"width\":1048576"), "width"),
    ] {
        let err = with(&good.to_json().replace(edit.0, edit.1));
        assert!(
            matches!(&err, Error::Config { field: f, .. } if *f == field),
            "{field}: {err}"
        );
    }
    // A config that disagrees with the tensors is caught by the shapes.
    let err = with(&good.to_json().replace("\"z_dim\":20", "\"z_dim\":21"));
    assert!(matches!(err, Error::Shape { .. }), "{err}");
}

#[test]
fn missing_file_is_an_io_error() {
    let err = Model::load("/nonexistent/weights.safetensors").err().unwrap();
    assert!(
        matches!(&err, Error::Io { path, .. } if path.contains("nonexistent")),
        "{err}"
    );
}

#[test]
fn wrong_buffers_and_non_finite_inputs_are_rejected() {
    let config = Config {
        height: 16,
        width: 32,
        channels: 3,
        base_channels: 2,
        z_dim: 4,
        hidden_dim: 5,
        ..Config::COMMA
    };
    let model = Model::random(&config, 1, WeightDtype::F32).unwrap();
    let mut sim = Simulator::with_batch(&model, 2).unwrap();
    let (frame, z) = (config.frame_len(), config.z_dim);
    let mut code = vec![0.0; z];

    let err = sim.encode(&vec![0.0; frame - 1], &mut code).unwrap_err();
    assert!(
        matches!(err, Error::NotWholeItems { buffer: "frames", item_len, found } if item_len == frame && found == frame - 1)
    );
    assert!(matches!(sim.encode(&[], &mut code), Err(Error::NotWholeItems { .. })));
    assert!(matches!(
        sim.encode(&vec![0.0; 3 * frame], &mut code),
        Err(Error::BatchTooLarge { max: 2, found: 3 })
    ));
    let err = sim.encode(&vec![0.0; frame], &mut vec![0.0; z + 1]).unwrap_err();
    assert!(matches!(err, Error::BufferLength { buffer: "z", expected, found } if expected == z && found == z + 1));
    let mut frame_in = vec![0.0; frame];
    frame_in[17] = f32::INFINITY;
    let err = sim.encode(&frame_in, &mut code).unwrap_err();
    assert!(
        matches!(
            err,
            Error::NonFinite {
                buffer: "frames",
                index: 17,
                ..
            }
        ),
        "{err}"
    );

    let mut out = vec![0.0; frame];
    assert!(matches!(
        sim.generate(&code, &mut out[1..]),
        Err(Error::BufferLength { buffer: "frames", .. })
    ));
    assert!(matches!(
        sim.generate(&[f32::NAN; 4], &mut out),
        Err(Error::NonFinite { buffer: "z", .. })
    ));

    let (mut h, mut next) = (vec![0.0; 5], vec![0.0; z]);
    assert!(matches!(
        sim.transition(&code, &mut h, &[0.0], &mut next),
        Err(Error::BufferLength { buffer: "action", .. })
    ));
    assert!(matches!(
        sim.transition(&code, &mut h[1..], &[0.0; 2], &mut next),
        Err(Error::BufferLength { buffer: "h", .. })
    ));
    h[0] = f32::NAN;
    assert!(matches!(
        sim.transition(&code, &mut h, &[0.0; 2], &mut next),
        Err(Error::NonFinite { buffer: "h", .. })
    ));

    // Rollouts: one action per transition, at least one prediction.
    let seeds = vec![0.0; 3 * frame];
    let err = sim.rollout(&seeds, &[0.0; 4], &mut code, None).unwrap_err();
    assert!(
        matches!(
            err,
            Error::BufferLength {
                buffer: "actions",
                expected: 6,
                found: 4
            }
        ),
        "{err}"
    );
    assert!(matches!(
        sim.rollout(&seeds, &[0.0; 5], &mut code, None),
        Err(Error::NotWholeItems { .. })
    ));
    assert!(matches!(
        sim.rollout(&seeds, &[0.0; 8], &mut code, None),
        Err(Error::BufferLength { buffer: "codes", .. })
    ));
    let mut codes = vec![0.0; 2 * z];
    let mut frames = vec![0.0; frame];
    let err = sim
        .rollout(&seeds, &[0.0; 8], &mut codes, Some(&mut frames))
        .unwrap_err();
    assert!(matches!(err, Error::BufferLength { buffer: "frames", .. }), "{err}");
    assert!(matches!(
        sim.rollout(&seeds, &[f32::NAN; 8], &mut codes, None),
        Err(Error::NonFinite { .. })
    ));
    sim.rollout(&seeds, &[0.0; 8], &mut codes, None).unwrap();

    // Random models validate their config too.
    assert!(Model::random(&Config { height: 40, ..config }, 1, WeightDtype::F32).is_err());
}

/// Plans that overflow or that no allocator can serve are errors naming their size, not
/// aborts, wrapped sizes or panics (`with_batch(1 << 63)` once wrapped to empty buffers).
#[test]
fn unaffordable_plans_are_errors() {
    let model = Model::from_bytes(&fixture_bytes()).unwrap();
    for batch in [1 << 40, 1 << 63, usize::MAX] {
        let err = Simulator::with_batch(&model, batch).err().unwrap();
        assert!(matches!(err, Error::OutOfMemory { .. }), "batch {batch}: {err}");
        assert!(Plan::new(model.config(), batch, 1).is_err() || batch == 1 << 40);
    }
    let err = Simulator::with_batch(&model, 1 << 40).err().unwrap();
    assert!(
        matches!(err, Error::OutOfMemory { bytes: Some(b), .. } if b > 1 << 50),
        "{err}"
    );
    // What a plan needs is known before anything is allocated.
    let plan = Plan::new(model.config(), 4, 2).unwrap();
    let sim = Simulator::with_batch(&model, 4).unwrap().with_threads(2).unwrap();
    assert_eq!(sim.buffer_bytes(), plan.bytes());
    // Configs past the bounds never reach planning: the 4096x4096 file with 1000
    // channels, and a random model with z = hidden = 65536 (17 GB of weights).
    let (tensors, mut meta) = fixture_parts();
    let good = Config::from_json(&meta["drivesim.config"]).unwrap();
    let huge = Config {
        height: 4096,
        width: 4096,
        channels: 1000,
        ..good
    };
    meta.insert("drivesim.config".into(), huge.to_json());
    let err = load_err(&write(&tensors, meta));
    assert!(matches!(err, Error::Config { field: "channels", .. }), "{err}");
    let wide = Config {
        z_dim: 65536,
        hidden_dim: 65536,
        ..good
    };
    let err = Model::random(&wide, 1, WeightDtype::F32).err().unwrap();
    assert!(matches!(err, Error::Config { field: "z_dim", .. }), "{err}");
}

/// Values no trained model has are refused at load, naming the tensor and the first bad index.
#[test]
fn impossible_weights_are_rejected() {
    let cases: [(&str, usize, f32); 4] = [
        ("encoder.conv1.weight", 7, f32::NAN),
        ("generator.deconv2.bias", 0, f32::INFINITY),
        ("transition.W", 3, f32::NAN),
        ("encoder.bn2.running_var", 5, -0.5),
    ];
    for (name, index, value) in cases {
        let (mut tensors, meta) = fixture_parts();
        let t = tensors.get_mut(name).unwrap();
        t.data[index * 4..][..4].copy_from_slice(&value.to_le_bytes());
        let err = load_err(&write(&tensors, meta));
        assert!(
            matches!(&err, Error::BadWeight { name: n, index: i, .. } if n == name && *i == index),
            "{name}: {err}"
        );
    }
}

/// `weights/README.md`: exactly the config's tensors, all in one dtype.
#[test]
fn extra_tensors_and_mixed_dtypes_are_rejected() {
    let (mut tensors, meta) = fixture_parts();
    tensors.insert(
        "encoder.extra".into(),
        Tensor {
            dtype: Dtype::F32,
            shape: vec![1],
            data: vec![0; 4],
        },
    );
    let err = load_err(&write(&tensors, meta.clone()));
    assert!(
        matches!(&err, Error::UnexpectedTensor { name } if name == "encoder.extra"),
        "{err}"
    );

    let (mut tensors, _) = fixture_parts();
    let t = tensors.get_mut("transition.b").unwrap();
    t.dtype = Dtype::BF16;
    t.data = t.data.chunks_exact(4).flat_map(|b| [b[2], b[3]]).collect();
    let err = load_err(&write(&tensors, meta));
    assert!(
        matches!(&err, Error::MixedDtypes { name, found, expected } if name == "transition.b" && found == "BF16" && expected == "F32"),
        "{err}"
    );
}

/// Frames lie in [-1, 1]; a finite value outside (one `f32::MAX` pixel once gave NaN codes
/// with `Ok`) is an error, and an overflowing result is never returned as `Ok`.
#[test]
fn out_of_range_frames_and_overflowing_results_are_errors() {
    let model = Model::from_bytes(&fixture_bytes()).unwrap();
    let c = *model.config();
    let mut sim = Simulator::new(&model).unwrap();
    let mut frame = vec![0.5; c.frame_len()];
    frame[9] = f32::MAX;
    let mut z = vec![0.0; c.z_dim];
    let err = sim.encode(&frame, &mut z).unwrap_err();
    assert!(
        matches!(
            err,
            Error::FrameValue {
                buffer: "frames",
                index: 9,
                ..
            }
        ),
        "{err}"
    );
    frame[9] = -1.0001;
    assert!(matches!(sim.encode(&frame, &mut z), Err(Error::FrameValue { .. })));
    let err = sim.rollout(&frame, &[0.0; 2], &mut z, None).unwrap_err();
    assert!(
        matches!(
            err,
            Error::FrameValue {
                buffer: "seed_frames",
                ..
            }
        ),
        "{err}"
    );
    frame[9] = 1.0;
    sim.encode(&frame, &mut z).unwrap();

    // Codes have no documented range: huge ones overflow inside the networks, whose tanh and
    // ReLU may turn that into finite values. Either way, an `Ok` result is finite.
    let huge: Vec<f32> = (0..c.z_dim)
        .map(|i| if i % 2 == 0 { f32::MAX } else { -f32::MAX })
        .collect();
    let (mut h, mut next) = (vec![0.0; c.hidden_dim], vec![0.0; c.z_dim]);
    let mut out = vec![0.0; c.frame_len()];
    let ok_is_finite = |result: Result<(), Error>, outputs: &[&[f32]]| match result {
        Ok(()) => assert!(outputs.iter().all(|o| o.iter().all(|v| v.is_finite()))),
        Err(err) => assert!(matches!(err, Error::NonFiniteOutput { .. }), "{err}"),
    };
    let result = sim.transition(&huge, &mut h, &[1.0, 0.0], &mut next);
    ok_is_finite(result, &[&h, &next]);
    let result = sim.generate(&huge, &mut out);
    ok_is_finite(result, &[&out]);

    // Finite but huge weights overflow the encoder's linear mean and the transition's `A h`.
    let (mut tensors, meta) = fixture_parts();
    for name in ["encoder.mean.weight", "transition.A"] {
        let t = tensors.get_mut(name).unwrap();
        t.data = (0..t.data.len() / 4).flat_map(|_| f32::MAX.to_le_bytes()).collect();
    }
    let model = Model::from_bytes(&write(&tensors, meta)).unwrap();
    let mut sim = Simulator::new(&model).unwrap();
    let err = sim.encode(&frame, &mut z).unwrap_err();
    assert!(matches!(err, Error::NonFiniteOutput { buffer: "z", .. }), "{err}");
    h.fill(0.5);
    let err = sim
        .transition(&vec![0.0; c.z_dim], &mut h, &[1.0, 0.0], &mut next)
        .unwrap_err();
    assert!(matches!(err, Error::NonFiniteOutput { buffer: "z_next", .. }), "{err}");
}
