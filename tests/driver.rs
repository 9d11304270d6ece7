//! Driver files: a policy head apart from the world it was learnt in. Written from a weight
//! file, it drives as that file's policy did; given another world, or something that is not a
//! driver file, it is refused with a typed error; the shipped driver belongs to the shipped world.

mod common;

use common::{fixture_path, values, with_f32_tensors};
use drivesim::{driver_file, world_fingerprint, Error, HeadKind, Model, Simulator};
use safetensors::SafeTensors;

fn world() -> Vec<u8> {
    std::fs::read(fixture_path("small_f32.safetensors")).unwrap()
}

/// `world` with a policy head of `width` (and a pace head, which a driver file leaves out).
fn learnt(world: &[u8], width: usize, seed: u64) -> Vec<u8> {
    let config = *Model::from_bytes(world).unwrap().config();
    let cols = config.z_dim + config.hidden_dim;
    let head = |prefix: &str, outputs: usize, width: usize, seed: u64| {
        [
            (
                format!("{prefix}.hidden.weight"),
                vec![width, cols],
                values(seed, width * cols, 0.3),
            ),
            (
                format!("{prefix}.hidden.bias"),
                vec![width],
                values(seed + 1, width, 0.1),
            ),
            (
                format!("{prefix}.output.weight"),
                vec![outputs, width],
                values(seed + 2, outputs * width, 0.3),
            ),
            (
                format!("{prefix}.output.bias"),
                vec![outputs],
                values(seed + 3, outputs, 0.1),
            ),
        ]
    };
    let tensors: Vec<_> = head("policy", 2, width, seed)
        .into_iter()
        .chain(head("pace", 1, 7, seed + 9))
        .collect();
    let added: Vec<_> = tensors
        .iter()
        .map(|(n, s, v)| (n.as_str(), s.clone(), v.clone()))
        .collect();
    with_f32_tensors(world, &added)
}

fn actions(model: &Model, batch: usize) -> Vec<f32> {
    let config = model.config();
    let (z, h) = (
        values(40, batch * config.z_dim, 2.0),
        values(41, batch * config.hidden_dim, 0.9),
    );
    let mut out = vec![0.0; batch * 2];
    Simulator::with_batch(model, batch)
        .unwrap()
        .act(&z, &h, &mut out)
        .unwrap();
    out
}

#[test]
fn a_driver_file_drives_as_the_policy_it_was_written_from() {
    let (world, file) = (world(), learnt(&world(), 13, 1));
    let driver = driver_file(&file).unwrap();
    assert_eq!(driver, driver_file(&file).unwrap(), "the same bytes each time");
    let read = SafeTensors::deserialize(&driver).unwrap();
    let mut names = read.names();
    names.sort();
    assert_eq!(
        names,
        [
            "policy.hidden.bias",
            "policy.hidden.weight",
            "policy.output.bias",
            "policy.output.weight"
        ]
    );
    // Neither the driver nor the pace head is the world: both files hold the same one.
    assert_eq!(world_fingerprint(&world).unwrap(), world_fingerprint(&file).unwrap());
    let driven = Model::from_bytes_with_driver(&world, &driver).unwrap();
    let original = Model::from_bytes(&file).unwrap();
    assert_eq!(original.head_width(HeadKind::Pace), Some(7));
    assert_eq!(
        (driven.policy_width(), driven.head_width(HeadKind::Pace)),
        (Some(13), None)
    );
    let bits = |v: Vec<f32>| v.into_iter().map(f32::to_bits).collect::<Vec<_>>();
    assert_eq!(bits(actions(&driven, 6)), bits(actions(&original, 6)));
    // Another driver of the same world drives otherwise, in place of the world's own policy.
    let other = driver_file(&learnt(&world, 13, 50)).unwrap();
    let driven_other = Model::from_bytes_with_driver(&file, &other).unwrap();
    assert_ne!(bits(actions(&driven_other, 6)), bits(actions(&original, 6)));
}

#[test]
fn a_driver_is_refused_by_another_world_and_bad_files_are_named() {
    let world = world();
    let driver = driver_file(&learnt(&world, 5, 1)).unwrap();
    let a = SafeTensors::deserialize(&world)
        .unwrap()
        .tensor("transition.a")
        .unwrap()
        .data()
        .to_vec();
    let mut nudged: Vec<f32> = a
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
        .collect();
    nudged[0] += 1e-3;
    let other_world = with_f32_tensors(&world, &[("transition.a", vec![nudged.len()], nudged)]);
    let (here, there) = (
        world_fingerprint(&other_world).unwrap(),
        world_fingerprint(&world).unwrap(),
    );
    assert_ne!(here, there);
    match Model::from_bytes_with_driver(&other_world, &driver) {
        Err(Error::OtherWorld { world, learnt_in }) => assert_eq!((world, learnt_in), (here, there)),
        other => panic!("expected OtherWorld, got {:?}", other.map(|_| ())),
    }
    // A weight file is not a driver file: no world named.
    let whole = learnt(&world, 5, 1);
    assert!(matches!(
        Model::from_bytes_with_driver(&world, &whole),
        Err(Error::Metadata { .. })
    ));
    // A driver file with a tensor that is not the policy's.
    let extra = with_f32_tensors(&driver, &[("pace.output.bias", vec![1], vec![0.0])]);
    assert!(matches!(
        Model::from_bytes_with_driver(&world, &extra),
        Err(Error::UnexpectedTensor { name }) if name == "pace.output.bias"
    ));
    assert!(matches!(
        Model::from_bytes_with_driver(&world, &driver[..driver.len() - 3]),
        Err(Error::Malformed { .. })
    ));
    assert!(matches!(driver_file(&world), Err(Error::NoPolicy)));
    assert!(matches!(world_fingerprint(b"not a file"), Err(Error::Malformed { .. })));
}

#[test]
fn the_shipped_driver_was_learnt_in_the_shipped_world() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("weights");
    let world = std::fs::read(root.join("default.safetensors")).unwrap();
    let driver = std::fs::read(root.join("dreamt.safetensors")).unwrap();
    let model = Model::from_bytes_with_driver(&world, &driver).unwrap();
    assert_eq!(model.policy_width(), Some(64));
}
