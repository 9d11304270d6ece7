//! What the fuzzers (`fuzz_targets/`) and the stable mutation test (`tests/fuzz_smoke.rs`) do
//! with each input: everything a user would, where any panic or abort is a bug.
#![allow(dead_code)] // each fuzz target uses one of these

use drivesim::{Episodes, Model, Simulator};

/// Loads `bytes` as a weight file and, if that succeeds, runs every network once. Returns
/// whether the networks ran.
pub fn weights(bytes: &[u8]) -> bool {
    let Ok(model) = Model::from_bytes(bytes) else {
        return false;
    };
    let c = *model.config();
    // A file small enough to fuzz can still describe frames too large to run quickly: the
    // plan must succeed or fail cleanly, but only small ones are run.
    let Ok(sim) = Simulator::new(&model) else { return false };
    if sim.buffer_bytes() > 64 << 20 {
        return false;
    }
    let mut sim = sim;
    let frame = vec![0.25; c.frame_len()];
    let (mut z, mut h, mut out) = (vec![0.0; c.z_dim], vec![0.0; c.hidden_dim], vec![0.0; c.frame_len()]);
    let action = vec![0.5; c.action_dim];
    let _ = sim.encode(&frame, &mut z);
    let mut z_next = vec![0.0; c.z_dim];
    let _ = sim.transition(&z, &mut h, &action, &mut z_next);
    let _ = sim.transition_fed_back(&mut h, &action, &mut z_next);
    let _ = sim.generate(&z_next, &mut out);
    let mut codes = vec![0.0; 2 * c.z_dim];
    let _ = sim.rollout(&frame, &[action.clone(), action].concat(), &mut codes, None);
    true
}

/// Reads `bytes` as an episodes file (gzipped or not) and, if that succeeds, every episode's
/// first and last frame and an index past the end. Returns whether it loaded.
pub fn episodes(bytes: &[u8]) -> bool {
    let Ok(episodes) = Episodes::from_bytes(bytes) else {
        return false;
    };
    let (height, width) = episodes.frame_size();
    let mut frame = vec![0.0; height * width * Episodes::CHANNELS];
    for i in 0..=episodes.len() {
        let Ok(episode) = episodes.episode(i) else { continue };
        for index in [0, episode.len().saturating_sub(1), episode.len(), usize::MAX] {
            let _ = episode.frame_f32(index, &mut frame);
        }
    }
    true
}

/// Loads `bytes` as a driver file for the small fixture's world and, if that succeeds, runs the
/// driver once. Returns whether it loaded.
pub fn driver(bytes: &[u8]) -> bool {
    static WORLD: &[u8] = include_bytes!("../fixtures/small_f32.safetensors");
    let Ok(model) = Model::from_bytes_with_driver(WORLD, bytes) else {
        return false;
    };
    let c = *model.config();
    let Ok(mut sim) = Simulator::new(&model) else {
        return false;
    };
    let mut action = vec![0.0; c.action_dim];
    let _ = sim.act(&vec![0.5; c.z_dim], &vec![0.1; c.hidden_dim], &mut action);
    true
}

/// Loads `bytes` as a sampler file for the small fixture's world and, if that succeeds, samples
/// once through its texture net. Returns whether it loaded.
pub fn sampler(bytes: &[u8]) -> bool {
    static WORLD: &[u8] = include_bytes!("../fixtures/small_f32.safetensors");
    let Ok(model) = Model::from_bytes_with_sampler(WORLD, bytes) else {
        return false;
    };
    let c = *model.config();
    let Ok(mut sim) = Simulator::new(&model) else {
        return false;
    };
    let mut z = vec![0.5; c.z_dim];
    if sim.set_sampling(1.0, 3).is_ok() {
        let _ = sim.sample(&vec![0.1; c.hidden_dim], 0, &mut z);
    }
    true
}
