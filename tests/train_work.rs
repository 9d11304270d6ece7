//! The count of each training step's work per thread (`--features train`): at 16 threads no
//! thread's share of either step exceeds the mean by more than 10 %, for the default and comma
//! configs (cutting the convolutions' weight gradients by output channels alone left 1.40 to the
//! default VAE-GAN step, and the default transition's products by rows alone 2.53); and the
//! count is of the step's work itself, the same total at every thread count.
#![cfg(feature = "train")]

use drivesim::train::{TransitionPlan, VaeGanPlan};
use drivesim::{Config, Error};

const DEFAULT: Config = Config {
    base_channels: 32,
    z_dim: 128,
    hidden_dim: 256,
    ..Config::COMMA
};

#[test]
fn sixteen_threads_get_even_shares() {
    for config in [DEFAULT, Config::COMMA] {
        let vae_gan = VaeGanPlan::new(&config, 64, 1).unwrap();
        let transition = TransitionPlan::new(&config, 256, 15).unwrap();
        for (step, work) in [("vae_gan", vae_gan.work(16)), ("transition", transition.work(16))] {
            let work = work.unwrap();
            assert!(
                work.imbalance() <= 1.1,
                "{step} z={}: imbalance {:.3} at 16 threads: {:?}",
                config.z_dim,
                work.imbalance(),
                work.parts
            );
        }
    }
}

#[test]
fn the_count_is_the_steps_work_at_every_thread_count() {
    let (z, h, cols, batch, steps) = (128u64, 256u64, 386u64, 256u64, 14u64);
    let transition = TransitionPlan::new(&DEFAULT, 256, 15).unwrap();
    let one = transition.work(1).unwrap();
    // One thread does it all: no imbalance, its share the whole.
    assert_eq!(one.imbalance(), 1.0);
    assert_eq!(one.largest(), one.total());
    // The products of every step: [W | V | U] x, A h, then [Aᵀ | Wᵀ] on the way back.
    let products = one.parts.iter().find(|p| p.name == "products over a step").unwrap();
    assert_eq!(products.total, steps * batch * (h * cols + z * h + h * (z + h)));
    let vae_gan = VaeGanPlan::new(&DEFAULT, 64, 1).unwrap();
    for threads in [2, 3, 7, 16, 32] {
        for (a, b) in [
            (transition.work(threads).unwrap(), &one),
            (vae_gan.work(threads).unwrap(), &vae_gan.work(1).unwrap()),
        ] {
            assert_eq!(a.total(), b.total(), "{threads} threads");
            assert!(a.largest() >= a.total() / threads as u64 && a.largest() <= a.total());
        }
    }
    // Too many threads is the planner's error, not a count.
    assert!(matches!(
        transition.work(100_000),
        Err(Error::Config { field: "threads", .. })
    ));
}
