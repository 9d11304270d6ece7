//! Sampler files: a texture net apart from the world whose transition it was learnt for. Written
//! from a weight file that is that world but for its texture net, it draws that file's futures
//! in the world; another world, a file with something else, or one that is not a sampler file is
//! refused with a typed error; the shipped judge belongs to the shipped world.

mod common;

use common::{fixture_path, values, with_f32_tensors, with_texture};
use drivesim::{driver_file, sampler_file, world_fingerprint, Error, Model, Simulator};
use safetensors::SafeTensors;

fn world() -> Vec<u8> {
    with_texture(&std::fs::read(fixture_path("small_f32.safetensors")).unwrap(), 9, 20)
}

/// Three steps of the transition from fixed states, each next code its mean, or sampled at
/// `temperature` above 0, as bits.
fn futures(model: &Model, temperature: f32) -> Vec<u32> {
    let config = *model.config();
    let batch = 5;
    let mut sim = Simulator::with_batch(model, batch).unwrap();
    if temperature > 0.0 {
        sim.set_sampling(temperature, 7).unwrap();
    }
    let mut h = values(30, batch * config.hidden_dim, 0.8);
    let mut z = values(31, batch * config.z_dim, 1.0);
    let actions: Vec<f32> = (0..batch).flat_map(|i| [20.0, i as f32 * 0.2 - 0.4]).collect();
    let mut out = Vec::new();
    for step in 0..3 {
        let mut next = vec![0.0; batch * config.z_dim];
        sim.transition(&z, &mut h, &actions, &mut next).unwrap();
        if temperature > 0.0 {
            sim.sample(&h, step, &mut next).unwrap();
        }
        out.extend(next.iter().map(|v| v.to_bits()));
        z = next;
    }
    out
}

#[test]
fn a_sampler_file_draws_the_futures_of_the_net_it_was_written_from() {
    let world = world();
    let other = with_texture(&world, 6, 60); // the same world, another (narrower) texture net
    let sampler = sampler_file(&other, &world).unwrap();
    assert_eq!(
        sampler,
        sampler_file(&other, &world).unwrap(),
        "the same bytes each time"
    );
    let read = SafeTensors::deserialize(&sampler).unwrap();
    let mut names = read.names();
    names.sort();
    assert_eq!(
        names,
        [
            "transition.texture.hidden.bias",
            "transition.texture.hidden.weight",
            "transition.texture.output.bias",
            "transition.texture.output.weight"
        ]
    );
    let (_, header) = SafeTensors::read_metadata(&sampler).unwrap();
    assert_eq!(
        header.metadata().as_ref().unwrap()["drivesim.world"],
        world_fingerprint(&world).unwrap()
    );
    let dreamt = Model::from_bytes_with_sampler(&world, &sampler).unwrap();
    let (own, original) = (Model::from_bytes(&world).unwrap(), Model::from_bytes(&other).unwrap());
    assert_eq!(dreamt.texture_width(), Some(6));
    assert_eq!(futures(&dreamt, 1.3), futures(&original, 1.3));
    assert_ne!(futures(&dreamt, 1.3), futures(&own, 1.3));
    // The mean dream is the world's: the sampler only draws the futures.
    assert_eq!(futures(&dreamt, 0.0), futures(&own, 0.0));
}

#[test]
fn a_sampler_of_another_world_and_bad_files_are_refused() {
    let world = world();
    let sampler = sampler_file(&with_texture(&world, 6, 60), &world).unwrap();
    let config = *Model::from_bytes(&world).unwrap().config();
    let z = config.z_dim;
    let nudged = with_f32_tensors(&world, &[("transition.a", vec![z], values(70, z, 0.5))]);
    assert!(matches!(
        Model::from_bytes_with_sampler(&nudged, &sampler),
        Err(Error::OtherWorld { .. })
    ));
    // Written for a world whose transition is not the file's.
    assert!(matches!(
        sampler_file(&with_texture(&nudged, 6, 60), &world),
        Err(Error::OtherWorld { .. })
    ));
    // A file without a texture net has no sampler to give.
    let plain = std::fs::read(fixture_path("small_f32.safetensors")).unwrap();
    assert!(matches!(sampler_file(&plain, &plain), Err(Error::NoSampling)));
    // A weight file names no world; a driver file of this world holds no texture net.
    assert!(matches!(
        Model::from_bytes_with_sampler(&world, &world),
        Err(Error::Metadata { .. })
    ));
    let cols = config.z_dim + config.hidden_dim;
    let learnt = with_f32_tensors(
        &world,
        &[
            ("policy.hidden.weight", vec![4, cols], values(80, 4 * cols, 0.3)),
            ("policy.hidden.bias", vec![4], values(81, 4, 0.1)),
            ("policy.output.weight", vec![2, 4], values(82, 8, 0.3)),
            ("policy.output.bias", vec![2], values(83, 2, 0.1)),
        ],
    );
    let driver = driver_file(&learnt).unwrap();
    assert!(matches!(
        Model::from_bytes_with_sampler(&world, &driver),
        Err(Error::MissingTensor { name }) if name == "transition.texture.hidden.weight"
    ));
    let extra = with_f32_tensors(&sampler, &[("transition.a", vec![1], vec![0.0])]);
    assert!(matches!(
        Model::from_bytes_with_sampler(&world, &extra),
        Err(Error::UnexpectedTensor { name }) if name == "transition.a"
    ));
    assert!(matches!(
        Model::from_bytes_with_sampler(&world, &sampler[..sampler.len() - 3]),
        Err(Error::Malformed { .. })
    ));
}

#[test]
fn the_shipped_judge_was_learnt_for_the_shipped_world() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("weights");
    let world = std::fs::read(root.join("default.safetensors")).unwrap();
    let judge = std::fs::read(root.join("judge.safetensors")).unwrap();
    let model = Model::from_bytes_with_sampler(&world, &judge).unwrap();
    let own = Model::from_bytes(&world).unwrap();
    assert_eq!(model.texture_width(), Some(256));
    assert_ne!(futures(&model, 1.2), futures(&own, 1.2));
    assert_eq!(futures(&model, 0.0), futures(&own, 0.0));
}
