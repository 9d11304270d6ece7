//! How one training step's work falls to its threads, counted from the plans (the same on any
//! machine): for the default and comma configs, the VAE-GAN step (batch 64) and the transition
//! step (batch 256, windows of 15 codes), the largest thread's share of each part against the
//! mean share, and the step's imbalance (the parts' largest shares added, against the mean):
//! the speed-up over one thread is at most `threads / imbalance`.
//!
//! ```text
//! cargo run --release --features train --example work_count -- [--threads 1,2,4,8,16,32] [--parts]
//! ```
//! Lines: `work step=vae_gan config=default threads=16 imbalance=1.03 bound=15.5x`, and with
//! `--parts` one line per part: `part step=… threads=… name="weight gradients" share=…`.

use drivesim::train::{StepWork, TransitionPlan, VaeGanPlan};
use drivesim::Config;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let threads: Vec<usize> = match args.iter().position(|a| a == "--threads") {
        Some(i) => args
            .get(i + 1)
            .ok_or("--threads needs a list")?
            .split(',')
            .map(str::parse)
            .collect::<Result<_, _>>()?,
        None => vec![1, 2, 4, 8, 16, 32],
    };
    let parts = args.iter().any(|a| a == "--parts");
    let default = Config {
        base_channels: 32,
        z_dim: 128,
        hidden_dim: 256,
        ..Config::COMMA
    };
    for (name, config) in [("default", default), ("comma", Config::COMMA)] {
        let vae_gan = VaeGanPlan::new(&config, 64, 1)?;
        let transition = TransitionPlan::new(&config, 256, 15)?;
        for &t in &threads {
            print(&vae_gan.work(t)?, "vae_gan", name, parts);
            print(&transition.work(t)?, "transition", name, parts);
        }
    }
    Ok(())
}

fn print(work: &StepWork, step: &str, config: &str, parts: bool) {
    let (t, imbalance) = (work.threads, work.imbalance());
    let bound = t as f64 / imbalance;
    println!("work step={step} config={config} threads={t} imbalance={imbalance:.3} bound={bound:.1}x");
    if parts {
        for p in &work.parts {
            // The part's largest share against its mean, and its share of the step's mean.
            let mean = p.total as f64 / t as f64;
            let of_step = p.total as f64 / work.total() as f64;
            let (name, largest) = (p.name, p.largest as f64 / mean.max(1.0));
            println!("part step={step} config={config} threads={t} name={name:?} largest/mean={largest:.2} of_work={of_step:.3}");
        }
    }
}
