//! After `Simulator::new` (or `Environment::new`), encoding, stepping, generating and rolling
//! out allocate nothing.

use drivesim::{Config, Environment, Model, Simulator, WeightDtype};
#[path = "common/counting.rs"]
mod counting;

use counting::{counted, Counting};

#[global_allocator]
static GLOBAL: Counting = Counting;

#[test]
fn hot_paths_allocate_nothing() {
    let config = Config {
        height: 32,
        width: 48,
        channels: 3,
        base_channels: 4,
        z_dim: 12,
        hidden_dim: 10,
        ..Config::COMMA
    };
    for dtype in [WeightDtype::F32, WeightDtype::F16] {
        let model = Model::random(&config, 3, dtype).unwrap();
        for isa in drivesim::Isa::supported() {
            // Planning allocates the buffers it reports, and little else.
            let (sim, _, bytes) = counted(|| Simulator::with_batch(&model, 3).unwrap().with_isa(isa));
            assert!(
                bytes >= sim.buffer_bytes() && bytes <= sim.buffer_bytes() + 1024,
                "{bytes} bytes allocated, {} planned",
                sim.buffer_bytes()
            );
            // Worker threads are started here, before counting; dispatching to them is free.
            let mut sim = sim.with_threads(2).unwrap();
            // Every caller buffer is made before counting starts.
            let frames = vec![0.25f32; 3 * config.frame_len()];
            let actions = vec![0.5f32; 6 * config.action_dim];
            let mut z = vec![0.0; 3 * config.z_dim];
            let mut logsigma = vec![0.0; 3 * config.z_dim];
            let mut h = vec![0.0; 3 * config.hidden_dim];
            let mut z_next = vec![0.0; 3 * config.z_dim];
            let mut out = vec![0.0; 3 * config.frame_len()];
            let mut codes = vec![0.0; 4 * config.z_dim];
            let mut rollout_frames = vec![0.0; 4 * config.frame_len()];
            let mut bad = vec![0.0; 1];
            let mut candidate_codes = vec![0.0; 2 * 3 * config.z_dim];
            // An environment of 3 drives that owns a model of its own.
            let mut env = Environment::new(Model::random(&config, 3, dtype).unwrap(), 3, 3).unwrap();
            let mut env_frames = vec![0.0; 3 * config.frame_len()];
            let mut candidate_frames = vec![0.0; 2 * 3 * config.frame_len()];

            let ((), n, _) = counted(|| {
                sim.encode(&frames, &mut z).unwrap();
                sim.encode(&frames[..config.frame_len()], &mut z[..config.z_dim])
                    .unwrap();
                sim.encode_with_logsigma(&frames, &mut z, &mut logsigma).unwrap();
                sim.transition(&z, &mut h, &actions[..3 * config.action_dim], &mut z_next)
                    .unwrap();
                // Fed its own prediction: the folded step with f32 weights.
                sim.transition_fed_back(&mut h, &actions[..3 * config.action_dim], &mut z_next)
                    .unwrap();
                sim.generate(&z_next, &mut out).unwrap();
                sim.rollout(
                    &frames,
                    &actions[..(3 - 1 + 4) * config.action_dim],
                    &mut codes,
                    Some(&mut rollout_frames),
                )
                .unwrap();
                sim.rollout(
                    &frames[..config.frame_len()],
                    &actions[..4 * config.action_dim],
                    &mut codes,
                    None,
                )
                .unwrap();
                sim.rollout_candidates(
                    &h[..config.hidden_dim],
                    Some(&z[..config.z_dim]),
                    3,
                    &actions,
                    &mut candidate_codes,
                    Some(&mut candidate_frames),
                )
                .unwrap();
                env.reset_from_frames(&frames, &[]).unwrap();
                env.step(&actions[..3 * config.action_dim]).unwrap();
                env.step(&actions[..3 * config.action_dim]).unwrap();
                env.frames(&mut env_frames).unwrap();
                env.rollout_candidates(2, 3, &actions, &mut candidate_codes, None)
                    .unwrap();
                // Rejected calls report without allocating either.
                assert!(sim.generate(&bad, &mut out).is_err());
                bad[0] = f32::NAN;
                assert!(sim.encode(&frames[..config.frame_len()], &mut bad).is_err());
            });
            assert_eq!(n, 0, "{n} allocations with {dtype:?} weights on {isa:?}");
            assert!(out.iter().all(|v| v.is_finite()) && rollout_frames.iter().any(|&v| v != 0.0));
        }
    }
}
