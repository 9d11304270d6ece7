//! Sharing a frame's work among threads gives the single-threaded results.

mod common;

use common::relative_error;
use drivesim::{Config, Model, Simulator, WeightDtype};

#[test]
fn threads_agree_with_one_thread() {
    // Large enough that the dense layers are split too, the transition's included.
    let config = Config {
        height: 32,
        width: 64,
        base_channels: 16,
        z_dim: 1024,
        hidden_dim: 300,
        ..Config::COMMA
    };
    let model = Model::random(&config, 11, WeightDtype::F32).unwrap();
    let batch = 3;
    let frames: Vec<f32> = (0..batch * config.frame_len())
        .map(|i| ((i * 7919) % 2001) as f32 / 1000.0 - 1.0)
        .collect();
    let run = |threads: usize| {
        let mut sim = Simulator::with_batch(&model, batch).with_threads(threads).unwrap();
        assert_eq!(sim.threads(), threads.max(1));
        let mut z = vec![0.0; batch * config.z_dim];
        let mut out = vec![0.0; batch * config.frame_len()];
        sim.encode(&frames, &mut z).unwrap();
        sim.generate(&z, &mut out).unwrap();
        let mut single = vec![0.0; config.z_dim];
        sim.encode(&frames[..config.frame_len()], &mut single).unwrap();
        // Two steps from the same code, then one fed its own prediction (the folded step), so
        // that later steps start from a hidden state the threads wrote.
        let actions: Vec<f32> = (0..batch * config.action_dim).map(|i| i as f32 / 4.0 - 0.5).collect();
        let mut h = vec![0.0; batch * config.hidden_dim];
        let mut z_next = vec![0.0; batch * config.z_dim];
        for _ in 0..2 {
            sim.transition(&z, &mut h, &actions, &mut z_next).unwrap();
        }
        let predicted = z_next.clone();
        sim.transition(&predicted, &mut h, &actions, &mut z_next).unwrap();
        // Batch 1 splits each product by rows: two tasks per step.
        let mut h1 = vec![0.0; config.hidden_dim];
        let mut z1 = vec![0.0; config.z_dim];
        for _ in 0..2 {
            sim.transition(&single, &mut h1, &actions[..config.action_dim], &mut z1)
                .unwrap();
        }
        let predicted = z1.clone();
        sim.transition(&predicted, &mut h1, &actions[..config.action_dim], &mut z1)
            .unwrap();
        (z, out, single, [h, z_next, h1, z1])
    };
    let one = run(1);
    // Threads split a batch differently, and the kernels' summation order depends on the batch
    // size: the results agree to rounding, not bit for bit.
    for threads in [2, 3, 5] {
        let many = run(threads);
        assert!(relative_error(&many.0, &one.0) <= 1e-5, "encode, {threads} threads");
        assert!(relative_error(&many.1, &one.1) <= 1e-5, "generate, {threads} threads");
        assert!(
            relative_error(&many.2, &one.2) <= 1e-5,
            "encode batch 1, {threads} threads"
        );
        for (i, (a, b)) in many.3.iter().zip(&one.3).enumerate() {
            assert!(relative_error(a, b) <= 1e-5, "transition output {i}, {threads} threads");
        }
    }
}
