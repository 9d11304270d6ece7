//! The trainer's arena (`--features train`): it allocates what its plan says once, a step
//! allocates nothing, and a caller's buffer that is too small is an error naming both sizes.
//! One test in its own binary, so that no other test's allocations are counted.
#![cfg(feature = "train")]

use drivesim::train::{TransitionPlan, TransitionSettings, TransitionTrainer};
use drivesim::{Config, Error, Model, WeightDtype};
#[path = "common/counting.rs"]
mod counting;

use counting::{counted, Counting};

#[global_allocator]
static GLOBAL: Counting = Counting;

#[test]
fn arena_is_the_plan_and_steps_allocate_nothing() {
    let config = Config {
        z_dim: 20,
        hidden_dim: 36,
        ..Config::COMMA
    };
    let (batch, window) = (4, 15);
    let codes: Vec<f32> = (0..batch * window * 20).map(|i| (i as f32 * 0.1).sin()).collect();
    let actions: Vec<f32> = (0..batch * (window - 1) * 2).map(|i| (i as f32 * 0.3).cos()).collect();
    let mut predictions = vec![0.0; batch * (window - 1) * 20];
    let mut action_grad = vec![0.0; actions.len()];
    for dtype in [WeightDtype::F32, WeightDtype::F16] {
        let model = Model::random(&config, 1, dtype).unwrap();
        let plan = TransitionPlan::new(&config, batch, window).unwrap();
        let listed: usize = plan.buffers().map(|(_, bytes)| bytes).sum();
        assert_eq!(listed, plan.bytes());
        let settings = TransitionSettings::default();

        let (trainer, _, bytes) = counted(|| TransitionTrainer::new(&model, &plan, settings).unwrap());
        assert!(
            bytes >= plan.bytes() && bytes <= plan.bytes() + 512,
            "{bytes} bytes allocated, {} planned",
            plan.bytes()
        );
        let mut trainer = trainer.with_threads(2).unwrap();
        let ((), calls, _) = counted(|| {
            for _ in 0..3 {
                trainer.step(&codes, &actions, 1e-3).unwrap();
            }
            trainer.predict(&codes, &actions, &mut predictions).unwrap();
            trainer.action_gradients(&codes, &actions, &mut action_grad).unwrap();
        });
        assert_eq!(calls, 0, "{dtype:?}: allocations during steps");

        // The caller's arena: the plan's bytes exactly are enough, one float fewer is an error
        // naming both sizes, and nothing is allocated for the arena.
        let floats = plan.bytes() / 4;
        let mut arena = vec![0.0f32; floats];
        let (trainer, _, bytes) =
            counted(|| TransitionTrainer::with_arena(&model, &plan, settings, &mut arena).map(|_| ()));
        trainer.unwrap();
        assert!(bytes < 512, "{bytes} bytes allocated besides the caller's arena");
        let err = TransitionTrainer::with_arena(&model, &plan, settings, &mut arena[..floats - 1]).err();
        match err {
            Some(Error::ArenaTooSmall { needed, given }) => {
                assert_eq!((needed, given), (plan.bytes(), plan.bytes() - 4));
            }
            other => panic!("expected ArenaTooSmall, got {other:?}"),
        }
    }
}
