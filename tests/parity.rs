//! Every forward pass agrees with the PyTorch reference of the same weights
//! (`weights/drivesim_reference/fixtures.py` wrote the fixtures), on every instruction set this CPU has.

mod common;

use common::{fixture_path, levels, relative_error, tolerance, Io, FIXTURES};
use drivesim::{Config, Isa, Model, Simulator, WeightDtype};

fn check(what: &str, name: &str, isa: Isa, found: &[f32], expected: &[f32]) {
    let err = relative_error(found, expected);
    println!("{name:10} {:7} {what:16} relative error {err:.2e}", isa.level().name());
    assert!(
        err <= tolerance(name),
        "{name} {what} on {isa:?}: relative error {err:e} > {}",
        tolerance(name)
    );
}

/// Runs `f` for every fixture on every instruction set this CPU has.
fn each_fixture(f: impl Fn(&str, &Model, &Io, Simulator<&Model>)) {
    let levels = levels();
    for name in FIXTURES {
        let model = Model::load(fixture_path(&format!("{name}.safetensors"))).expect("fixture weights load");
        let io = Io::load(name);
        for &isa in &levels {
            f(
                name,
                &model,
                &io,
                Simulator::with_batch(&model, 2).unwrap().with_isa(isa),
            );
        }
    }
}

#[test]
fn encode_matches_pytorch() {
    each_fixture(|name, model, io, mut sim| {
        let z = model.config().z_dim;
        let frames = io.values("encode.frames");
        let (mut mean, mut logsigma) = (vec![0.0; 2 * z], vec![0.0; 2 * z]);
        sim.encode_with_logsigma(&frames, &mut mean, &mut logsigma).unwrap();
        check("encode mean", name, sim.isa(), &mean, &io.values("encode.mean"));
        check(
            "encode logsigma",
            name,
            sim.isa(),
            &logsigma,
            &io.values("encode.logsigma"),
        );
        // One frame at a time gives the same codes as the batch.
        let mut single = vec![0.0; z];
        sim.encode(&frames[frames.len() / 2..], &mut single).unwrap();
        check(
            "encode single",
            name,
            sim.isa(),
            &single,
            &io.values("encode.mean")[z..],
        );
    });
}

#[test]
fn generate_matches_pytorch() {
    each_fixture(|name, model, io, mut sim| {
        let mut frames = vec![0.0; 2 * model.config().frame_len()];
        sim.generate(&io.values("generate.z"), &mut frames).unwrap();
        check("generate", name, sim.isa(), &frames, &io.values("generate.frames"));
    });
}

#[test]
fn thirty_step_transition_matches_pytorch() {
    each_fixture(|name, model, io, mut sim| {
        let c = model.config();
        // Every step from the code given, or every step after the first fed its own prediction
        // (the folded step with f32 weights).
        for fed_back in [false, true] {
            let what = |output| format!("{output}{}", if fed_back { " fed back" } else { "" });
            let mut z = io.values("transition.z0");
            let mut h = io.values("transition.h0");
            let (mut zs, mut hs) = (Vec::new(), Vec::new());
            for (step, action) in io.values("transition.actions").chunks_exact(c.action_dim).enumerate() {
                let mut z_next = vec![0.0; c.z_dim];
                if fed_back && step > 0 {
                    sim.transition_fed_back(&mut h, action, &mut z_next).unwrap();
                } else {
                    sim.transition(&z, &mut h, action, &mut z_next).unwrap();
                }
                z = z_next;
                zs.extend_from_slice(&z);
                hs.extend_from_slice(&h);
            }
            let isa = sim.isa();
            check(&what("transition z"), name, isa, &zs, &io.values("transition.z"));
            check(&what("transition h"), name, isa, &hs, &io.values("transition.h"));
            let mut frame = vec![0.0; c.frame_len()];
            sim.generate(&z, &mut frame).unwrap();
            check(
                &what("frame after 30"),
                name,
                isa,
                &frame,
                &io.values("transition.frame"),
            );
        }
    });
}

/// Folding `V A` into `W` changes only rounding: over a long drive on the comma config, steps
/// fed their own prediction stay with two-product steps from the same codes.
#[test]
fn folded_steps_follow_the_two_product_step() {
    let model = Model::random(&Config::COMMA, 5, WeightDtype::F32).unwrap();
    let c = model.config();
    let mut sim = Simulator::with_batch(&model, 2).unwrap();
    let (mut z_fed, mut z) = (vec![0.5; 2 * c.z_dim], vec![0.5; 2 * c.z_dim]);
    let (mut h_fed, mut h) = (vec![0.0; 2 * c.hidden_dim], vec![0.0; 2 * c.hidden_dim]);
    let mut z_next = vec![0.0; 2 * c.z_dim];
    let (mut worst, mut identical) = (0.0f32, true);
    for step in 0..200 {
        let action = [(step as f32 / 10.0).sin(), 0.2, -0.4, (step as f32 / 7.0).cos()];
        if step == 0 {
            sim.transition(&z, &mut h_fed, &action, &mut z_fed).unwrap();
        } else {
            sim.transition_fed_back(&mut h_fed, &action, &mut z_fed).unwrap();
        }
        sim.transition(&z, &mut h, &action, &mut z_next).unwrap();
        core::mem::swap(&mut z, &mut z_next);
        worst = worst.max(relative_error(&z_fed, &z)).max(relative_error(&h_fed, &h));
        identical &= z_fed == z;
    }
    println!("worst relative error over 200 steps {worst:.2e}");
    assert!(worst <= 1e-5, "folded steps drifted by {worst:e}");
    // Rounding differs somewhere in 200 steps of 512 sums, so equal codes would mean the
    // folded step was never taken.
    assert!(!identical, "the folded step was never taken");
}

#[test]
fn rollout_matches_pytorch() {
    each_fixture(|name, model, io, mut sim| {
        let (shape, expected_codes) = io.get("rollout.codes");
        let mut codes = vec![0.0; expected_codes.len()];
        let mut frames = vec![0.0; shape[0] * model.config().frame_len()];
        let (seeds, actions) = (io.values("rollout.seed_frames"), io.values("rollout.actions"));
        sim.rollout(&seeds, &actions, &mut codes, Some(&mut frames)).unwrap();
        check("rollout codes", name, sim.isa(), &codes, &expected_codes);
        check("rollout frames", name, sim.isa(), &frames, &io.values("rollout.frames"));
        // Without frames the codes are the same.
        let mut again = vec![0.0; codes.len()];
        sim.rollout(&seeds, &actions, &mut again, None).unwrap();
        assert_eq!(again, codes);
        // Seeding with the encoded seed frames is the same rollout.
        let z = model.config().z_dim;
        let mut seed_codes = vec![0.0; seeds.len() / model.config().frame_len() * z];
        for (frame, code) in seeds
            .chunks_exact(model.config().frame_len())
            .zip(seed_codes.chunks_exact_mut(z))
        {
            sim.encode(frame, code).unwrap();
        }
        sim.rollout_from_codes(&seed_codes, &actions, &mut again, None).unwrap();
        assert_eq!(again, codes);
    });
}
