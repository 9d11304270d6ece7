//! Sampler files: a texture net apart from the world whose transition it was learnt for, and
//! the read-out where the sampler has one of its own. Written from a weight file that is that
//! world but for its texture net (and read-out), it draws that file's futures in the world;
//! another world, a file with something else, or one that is not a sampler file is refused with
//! a typed error; the shipped judge belongs to the shipped world.

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

/// `world` with its read-out (`transition.A`, `transition.a`) widened by `by` about `centre`,
/// as `python -m drivesim widen` widens one.
fn widened(world: &[u8], by: f32, centre: f32) -> Vec<u8> {
    let config = *Model::from_bytes(world).unwrap().config();
    let (z, hd) = (config.z_dim, config.hidden_dim);
    let file = SafeTensors::deserialize(world).unwrap();
    let floats = |name: &str| -> Vec<f32> {
        let data = file.tensor(name).unwrap().data().to_vec();
        data.chunks(4)
            .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
            .collect()
    };
    let big_a = floats("transition.A").iter().map(|v| by * v).collect();
    let small_a = floats("transition.a")
        .iter()
        .map(|v| by * v + (1.0 - by) * centre)
        .collect();
    with_f32_tensors(
        world,
        &[("transition.A", vec![z, hd], big_a), ("transition.a", vec![z], small_a)],
    )
}

#[test]
fn a_sampler_with_a_read_out_of_its_own_dreams_the_mean_of_the_file_it_came_from() {
    let world = world();
    // The small world is f32, so the read-out is folded into its feedback: that follows too.
    let other = widened(&with_texture(&world, 6, 60), 1.05, 0.3);
    let sampler = sampler_file(&other, &world).unwrap();
    let read = SafeTensors::deserialize(&sampler).unwrap();
    let mut names = read.names();
    names.sort();
    assert_eq!(names.len(), 6);
    assert_eq!(names[..2], ["transition.A", "transition.a"]);
    let dreamt = Model::from_bytes_with_sampler(&world, &sampler).unwrap();
    let (own, original) = (Model::from_bytes(&world).unwrap(), Model::from_bytes(&other).unwrap());
    assert_eq!(futures(&dreamt, 0.0), futures(&original, 0.0));
    assert_ne!(futures(&dreamt, 0.0), futures(&own, 0.0));
    assert_eq!(futures(&dreamt, 1.3), futures(&original, 1.3));
    // The world's own read-out is left out of a plain sampler, which stays four tensors.
    let plain = sampler_file(&with_texture(&world, 6, 60), &world).unwrap();
    assert_eq!(SafeTensors::deserialize(&plain).unwrap().names().len(), 4);
    // Half a read-out, or one of another shape, is refused.
    let config = *own.config();
    let (z, hd) = (config.z_dim, config.hidden_dim);
    let half = with_f32_tensors(&plain, &[("transition.a", vec![z], values(71, z, 0.5))]);
    assert!(matches!(
        Model::from_bytes_with_sampler(&world, &half),
        Err(Error::MissingTensor { name }) if name == "transition.A"
    ));
    let wrong = with_f32_tensors(&sampler, &[("transition.A", vec![hd, z], values(72, z * hd, 0.5))]);
    assert!(matches!(
        Model::from_bytes_with_sampler(&world, &wrong),
        Err(Error::Shape { name, .. }) if name == "transition.A"
    ));
}

#[test]
fn a_sampler_of_another_world_and_bad_files_are_refused() {
    let world = world();
    let sampler = sampler_file(&with_texture(&world, 6, 60), &world).unwrap();
    let config = *Model::from_bytes(&world).unwrap().config();
    let hd = config.hidden_dim;
    let nudged = with_f32_tensors(&world, &[("transition.b", vec![hd], values(70, hd, 0.5))]);
    assert!(matches!(
        Model::from_bytes_with_sampler(&nudged, &sampler),
        Err(Error::OtherWorld { .. })
    ));
    // Written for a world whose transition is not the file's (but for a read-out, which a
    // sampler may carry).
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
    let extra = with_f32_tensors(&sampler, &[("transition.b", vec![1], vec![0.0])]);
    assert!(matches!(
        Model::from_bytes_with_sampler(&world, &extra),
        Err(Error::UnexpectedTensor { name }) if name == "transition.b"
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
    // Its read-out is the default's widened (`python -m drivesim widen`): so is its mean dream.
    assert_ne!(futures(&model, 0.0), futures(&own, 0.0));
}
