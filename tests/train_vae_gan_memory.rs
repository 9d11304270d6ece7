//! The VAE-GAN trainer's memory (`--features train`): it allocates what its plan measured,
//! once, and a step allocates nothing, with threads too. One test in its own binary, so that no
//! other test's allocations are counted.
#![cfg(feature = "train")]

use drivesim::train::{random_weight_file, VaeGanPlan, VaeGanSettings, VaeGanTrainer, VAE_GAN_LR};
use drivesim::Config;
#[path = "common/counting.rs"]
mod counting;

use counting::{counted, Counting};

#[global_allocator]
static GLOBAL: Counting = Counting;

#[test]
fn buffers_are_the_plan_and_steps_allocate_nothing() {
    let config = Config {
        height: 32,
        width: 64,
        base_channels: 8,
        z_dim: 12,
        hidden_dim: 16,
        ..Config::COMMA
    };
    let file = random_weight_file(&config, 3).unwrap();
    let batch = 3;
    let frames: Vec<f32> = (0..batch * config.frame_len())
        .map(|i| (i as f32 * 0.37).sin())
        .collect();
    let eps: Vec<f32> = (0..batch * config.z_dim).map(|i| (i as f32 * 0.7).cos()).collect();
    // Five threads: weight gradients cut by blocks of pixels and by groups of rows.
    for threads in [1, 2, 5] {
        let plan = VaeGanPlan::new(&config, batch, threads).unwrap();
        let listed: usize = plan.buffers().map(|(_, bytes)| bytes).sum();
        assert_eq!(listed, plan.bytes());
        let (trainer, _, bytes) = counted(|| VaeGanTrainer::new(&file, &plan, VaeGanSettings::default()).unwrap());
        // The buffers, plus the tensors read from the file on their way in and their names.
        assert!(
            bytes >= plan.bytes() && bytes <= plan.bytes() + 2 * file.len(),
            "{bytes} bytes allocated, {} planned",
            plan.bytes()
        );
        let mut trainer = trainer;
        let ((), calls, _) = counted(|| {
            for _ in 0..2 {
                trainer.step(&frames, &eps, &eps, VAE_GAN_LR).unwrap();
            }
            // A smaller batch than planned takes the same buffers.
            let one = config.frame_len();
            trainer
                .step(&frames[..one], &eps[..12], &eps[..12], VAE_GAN_LR)
                .unwrap();
        });
        assert_eq!(calls, 0, "{threads} threads: allocations during steps");
    }
}
