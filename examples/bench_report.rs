//! Times encode, generate and one transition step (from a given code, and fed back) and prints one
//! machine-readable line per measurement (read by `weights/drivesim_reference/compare.py`), plus the FMA peak
//! of this core per vector width.
//!
//! ```text
//! cargo run --release --example bench_report -- [--weights FILE | --z N [--hidden N] [--base N]] [--dtype f32|f16]
//!     [--batch 1,16] [--threads 1,2] [--networks encode,generate,transition,transition_fed_back,planner]
//!     [--seconds S]
//!     [--serve]
//! ```
//! Built with `--features train`, the network `train_transition` is one training step of the
//! transition (`drivesim::train`) on a batch of windows of 15 codes (read by
//! `weights/drivesim_reference/compare_train.py`), and `train_vae_gan` one VAE-GAN step of the encoder, generator
//! and discriminator on a batch of frames (`--base N` sets the base channels, 64 by default).
//! Lines: `isa level=avx2`, `peak width=256 threads=1 gflops=…` (for 1 and each `--threads`
//! count: the FMA peak of that many threads at once), and
//! `result network=encode batch=1 threads=1 median_ms=… gflop=…` (GFLOP per call, all taps;
//! with threads also `handoff_ns=…`, a cache line's round trip between two threads just after,
//! which tells the placements of a VM's vCPUs apart).
//! `--threads N` plans the simulator with `Simulator::with_threads(N)`.
//!
//! With `--serve` it times nothing by itself: after the peaks it prints `ready`, then reads
//! requests `NETWORK BATCH THREADS` from standard input, one per line, and answers each with
//! its `result` line, so that a caller can interleave drivesim's measurements with other
//! runtimes' on a noisy machine (`weights/drivesim_reference/compare.py` does).

#[path = "../benches/common/mod.rs"]
mod common;

use common::*;
use drivesim::{frames_from_rgb, Config, Isa, IsaLevel, Model, PixelLayout, Simulator, WeightDtype};
use std::collections::HashMap;
use std::hint::black_box;
use std::io::Write;
use std::time::{Duration, Instant};

/// `transition_fed_back` is a step fed the previous step's prediction, as in a rollout after
/// its seeds ([`Simulator::transition_fed_back`]: the folded step for f32 weights). Both steps count
/// the model's FLOPs.
/// `encode_rgb` encodes 8-bit frames (`frames_from_rgb`, then `encode`): what the Python
/// package's `Simulator.encode` does with a `uint8` array.
/// `planner` is a planner's inner loop: `Simulator::rollout_candidates` of BATCH candidates
/// for [`PLANNER_STEPS`] steps from one state and code, codes only (FLOPs counted as that many
/// steps of the model from codes, what a runtime without the crate's shortcuts computes).
const NETWORKS: [&str; 8] = [
    "encode",
    "encode_rgb",
    "generate",
    "transition",
    "transition_fed_back",
    PLANNER,
    TRAIN,
    TRAIN_VAE_GAN,
];

/// The planner's loop (see [`NETWORKS`]).
const PLANNER: &str = "planner";
/// Steps of each candidate in the planner's loop.
const PLANNER_STEPS: usize = 10;

/// One transition training step on `batch` windows of [`WINDOW`] codes (`--features train`).
const TRAIN: &str = "train_transition";
/// One VAE-GAN training step on `batch` frames (`--features train`).
const TRAIN_VAE_GAN: &str = "train_vae_gan";
/// Codes per training window, as `weights/drivesim_reference/train.py`.
#[cfg(feature = "train")]
const WINDOW: usize = 15;

fn arg<'a>(args: &'a [String], name: &str) -> Option<&'a str> {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .map(String::as_str)
}

/// Median wall time of `f` in ms: at least 5 runs and about `budget` in total.
fn median_ms(budget: Duration, mut f: impl FnMut()) -> f64 {
    f(); // warm-up: caches, page faults
    let start = Instant::now();
    let mut times = Vec::new();
    while times.len() < 5 || start.elapsed() < budget {
        let t = Instant::now();
        f();
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    times.sort_by(f64::total_cmp);
    times[times.len() / 2]
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let batches: Vec<usize> = arg(&args, "--batch")
        .unwrap_or("1,16")
        .split(',')
        .map(|b| b.parse().expect("--batch: comma-separated integers"))
        .collect();
    let thread_counts: Vec<usize> = arg(&args, "--threads")
        .unwrap_or("1")
        .split(',')
        .map(|t| t.parse().expect("--threads: comma-separated integers"))
        .collect();
    let networks: Vec<&str> = arg(&args, "--networks")
        .unwrap_or("encode,generate,transition")
        .split(',')
        .collect();
    if let Some(bad) = networks.iter().find(|n| !NETWORKS.contains(n)) {
        panic!("--networks: unknown network {bad:?} ({})", NETWORKS.join(", "));
    }
    let budget = Duration::from_secs_f64(arg(&args, "--seconds").map_or(2.0, |s| s.parse().expect("--seconds")));
    let dtype = match arg(&args, "--dtype").unwrap_or("f32") {
        "f16" => WeightDtype::F16,
        _ => WeightDtype::F32,
    };
    let model = match arg(&args, "--weights") {
        Some(path) => Model::load(path).expect("loading the weights"),
        None => {
            let z = arg(&args, "--z").map_or(512, |z| z.parse().expect("--z"));
            let hidden_dim = arg(&args, "--hidden").map_or(z, |h| h.parse().expect("--hidden"));
            let base_channels = arg(&args, "--base").map_or(64, |b| b.parse().expect("--base"));
            let config = Config {
                hidden_dim,
                base_channels,
                ..comma(z)
            };
            Model::random(&config, 2016, dtype).expect("valid config")
        }
    };
    let isa = Isa::best();
    println!("isa level={}", isa.level().name());
    let mut peak_threads = thread_counts.clone();
    peak_threads.push(1);
    peak_threads.sort_unstable();
    peak_threads.dedup();
    for threads in peak_threads {
        for (width, gflops) in fma_peak(threads) {
            println!("peak width={width} threads={threads} gflops={gflops:.2}");
        }
    }
    let mut sims = HashMap::new();
    if args.iter().any(|a| a == "--serve") {
        println!("ready");
        std::io::stdout().flush().expect("stdout");
        for line in std::io::stdin().lines() {
            let line = line.expect("reading a request");
            let request: Vec<&str> = line.split_whitespace().collect();
            let [network, batch, threads] = request[..] else {
                panic!("a request is NETWORK BATCH THREADS, got {line:?}");
            };
            assert!(NETWORKS.contains(&network), "unknown network {network:?}");
            let (batch, threads) = (batch.parse().expect("BATCH"), threads.parse().expect("THREADS"));
            answer(&mut sims, &model, network, batch, threads, budget);
        }
        return;
    }
    for (&threads, &batch) in thread_counts.iter().flat_map(|t| batches.iter().map(move |b| (t, b))) {
        for &network in &networks {
            answer(&mut sims, &model, network, batch, threads, budget);
        }
        // One simulator at a time: each holds its planned buffers.
        sims.clear();
    }
}

/// Times `network` on `batch` items with `threads` threads and prints its `result` line; the
/// simulators stay planned in `sims` for the next request.
fn answer<'m>(
    sims: &mut HashMap<(usize, usize), Simulator<&'m Model>>,
    model: &'m Model,
    network: &str,
    batch: usize,
    threads: usize,
    budget: Duration,
) {
    if network == TRAIN || network == TRAIN_VAE_GAN {
        let measure = if network == TRAIN {
            measure_training
        } else {
            measure_vae_gan
        };
        let (flops, ms) = measure(model, batch, threads, budget);
        report(network, batch, threads, ms, (batch as u64 * flops) as f64 / 1e9);
        return;
    }
    let sim = sims.entry((threads, batch)).or_insert_with(|| {
        Simulator::with_batch(model, batch)
            .and_then(|sim| sim.with_threads(threads))
            .expect("simulator planned and threads started")
    });
    let (flops, ms) = measure(sim, network, batch, budget);
    report(network, batch, threads, ms, (batch as u64 * flops) as f64 / 1e9);
}

/// Prints a measurement's `result` line; with threads, it also says how long a cache line took
/// to go between two threads just after (see [`handoff_ns`]).
fn report(network: &str, batch: usize, threads: usize, ms: f64, gflop: f64) {
    let handoff = if threads > 1 {
        format!(" handoff_ns={:.0}", handoff_ns())
    } else {
        String::new()
    };
    println!("result network={network} batch={batch} threads={threads} median_ms={ms:.4} gflop={gflop:.6}{handoff}");
    std::io::stdout().flush().expect("stdout");
}

/// The round trip of a cache line between two threads in nanoseconds (the median of 5 runs of
/// 2,000 trips). On a 2-vCPU VM it is about 50 when the host keeps the vCPUs on one die and
/// about 400 when it puts them on different dies, where every hand-off between a pool's threads
/// costs as much: two-thread timings are only comparable within one placement.
fn handoff_ns() -> f64 {
    use std::sync::atomic::{AtomicU64, Ordering};
    const TRIPS: u64 = 2_000;
    let mut runs: Vec<f64> = (0..5)
        .map(|_| {
            let ball = AtomicU64::new(0);
            std::thread::scope(|s| {
                // The other thread answers each odd value with the next even one.
                s.spawn(|| {
                    for trip in 0..TRIPS {
                        while ball.load(Ordering::Acquire) != 2 * trip + 1 {
                            std::hint::spin_loop();
                        }
                        ball.store(2 * trip + 2, Ordering::Release);
                    }
                });
                let start = Instant::now();
                for trip in 0..TRIPS {
                    ball.store(2 * trip + 1, Ordering::Release);
                    while ball.load(Ordering::Acquire) != 2 * trip + 2 {
                        std::hint::spin_loop();
                    }
                }
                start.elapsed().as_secs_f64() * 1e9 / TRIPS as f64
            })
        })
        .collect();
    runs.sort_by(f64::total_cmp);
    runs[2]
}

/// FLOPs of one item and the median ms of one call of `network` on `batch` items.
fn measure(sim: &mut Simulator<&Model>, network: &str, batch: usize, budget: Duration) -> (u64, f64) {
    let cfg = *sim.config();
    let frames = values(1, batch * cfg.frame_len(), 1.0);
    let codes = values(2, batch * cfg.z_dim, 1.0);
    let actions = values(3, batch * cfg.action_dim, 1.0);
    let mut out_frames = vec![0.0; batch * cfg.frame_len()];
    let mut out_codes = vec![0.0; batch * cfg.z_dim];
    let mut h = vec![0.0; batch * cfg.hidden_dim];
    match network {
        "encode" => (
            encode_flops(&cfg),
            median_ms(budget, || sim.encode(black_box(&frames), &mut out_codes).unwrap()),
        ),
        "encode_rgb" => {
            let rgb: Vec<u8> = frames.iter().map(|v| ((v + 1.0) * 127.5) as u8).collect();
            let mut floats = vec![0.0; frames.len()];
            let ms = median_ms(budget, || {
                frames_from_rgb(black_box(&rgb), PixelLayout::Hwc, &cfg, &mut floats).unwrap();
                sim.encode(&floats, &mut out_codes).unwrap()
            });
            (encode_flops(&cfg), ms)
        }
        "generate" => (
            generate_flops(&cfg),
            median_ms(budget, || sim.generate(black_box(&codes), &mut out_frames).unwrap()),
        ),
        "transition" => (
            transition_flops(&cfg),
            median_ms(budget, || {
                h.fill(0.0);
                sim.transition(black_box(&codes), &mut h, &actions, &mut out_codes)
                    .unwrap()
            }),
        ),
        PLANNER => {
            let (state, code) = (values(4, cfg.hidden_dim, 0.5), values(5, cfg.z_dim, 1.0));
            let actions = values(6, PLANNER_STEPS * batch * cfg.action_dim, 1.0);
            let mut codes = vec![0.0; PLANNER_STEPS * batch * cfg.z_dim];
            let ms = median_ms(budget, || {
                sim.rollout_candidates(&state, Some(black_box(&code)), batch, &actions, &mut codes, None)
                    .unwrap()
            });
            (PLANNER_STEPS as u64 * transition_flops(&cfg), ms)
        }
        _ => (
            transition_flops(&cfg),
            median_ms(budget, || {
                sim.transition_fed_back(&mut h, black_box(&actions), &mut out_codes)
                    .unwrap()
            }),
        ),
    }
}

/// FLOPs of one window and the median ms of one training step on `batch` windows.
#[cfg(feature = "train")]
fn measure_training(model: &Model, batch: usize, threads: usize, budget: Duration) -> (u64, f64) {
    use drivesim::train::{TransitionPlan, TransitionSettings, TransitionTrainer};
    let cfg = *model.config();
    let plan = TransitionPlan::new(&cfg, batch, WINDOW).expect("plan");
    let mut trainer = TransitionTrainer::new(model, &plan, TransitionSettings::default())
        .and_then(|t| t.with_threads(threads))
        .expect("trainer");
    let codes = values(4, batch * WINDOW * cfg.z_dim, 1.0);
    let actions = values(5, batch * (WINDOW - 1) * cfg.action_dim, 1.0);
    let ms = median_ms(budget, || {
        trainer.step(black_box(&codes), &actions, 1e-4).unwrap();
    });
    (train_transition_flops(&cfg, WINDOW), ms)
}

/// FLOPs of one frame and the median ms of one VAE-GAN step on `batch` frames, from seeded
/// random weights of `model`'s config.
#[cfg(feature = "train")]
fn measure_vae_gan(model: &Model, batch: usize, threads: usize, budget: Duration) -> (u64, f64) {
    use drivesim::train::{random_weight_file, VaeGanPlan, VaeGanSettings, VaeGanTrainer};
    let cfg = *model.config();
    let file = random_weight_file(&cfg, 2016).expect("weights");
    let plan = VaeGanPlan::new(&cfg, batch, threads).expect("plan");
    let mut trainer = VaeGanTrainer::new(&file, &plan, VaeGanSettings::default()).expect("trainer");
    let frames: Vec<f32> = values(6, batch * cfg.frame_len(), 1.0);
    let (eps, prior) = (values(7, batch * cfg.z_dim, 1.0), values(8, batch * cfg.z_dim, 1.0));
    // A small rate: the weights stay where they started, step after step.
    let ms = median_ms(budget, || {
        trainer.step(black_box(&frames), &eps, &prior, 1e-6).unwrap();
    });
    (train_vae_gan_flops(&cfg), ms)
}

#[cfg(not(feature = "train"))]
fn measure_vae_gan(_: &Model, _: usize, _: usize, _: Duration) -> (u64, f64) {
    panic!("{TRAIN_VAE_GAN} needs the train feature: cargo run --release --features train --example bench_report")
}

#[cfg(not(feature = "train"))]
fn measure_training(_: &Model, _: usize, _: usize, _: Duration) -> (u64, f64) {
    panic!("{TRAIN} needs the train feature: cargo run --release --features train --example bench_report")
}

/// Peak FMA throughput in GFLOP/s of `threads` threads at once (their sum), for each vector
/// width this CPU has. Measured, not assumed: two vCPUs of a VM may share one core's FMA units.
fn fma_peak(threads: usize) -> Vec<(usize, f64)> {
    let mut out = Vec::new();
    for (level, width) in [(IsaLevel::Neon, 128), (IsaLevel::Avx2, 256), (IsaLevel::Avx512, 512)] {
        if Isa::new(level).is_none() {
            continue;
        }
        let iters = 5_000_000u64;
        let mut best = f64::INFINITY;
        for _ in 0..10 {
            let t = Instant::now();
            std::thread::scope(|s| {
                for _ in 0..threads {
                    // SAFETY: `Isa::new` checked that the CPU has the features.
                    s.spawn(|| black_box(unsafe { peak::fma_loop(width, iters) }));
                }
            });
            best = best.min(t.elapsed().as_secs_f64());
        }
        // `CHAINS` accumulators, one FMA (2 FLOP per lane) each per iteration, on every thread.
        let flop = threads as u64 * iters * peak::CHAINS * 2 * (width as u64 / 32);
        out.push((width, flop as f64 / best / 1e9));
    }
    out
}

#[cfg(target_arch = "x86_64")]
mod peak {
    use std::arch::x86_64::*;

    /// Independent FMA chains: enough to cover 2 ports x 4-6 cycles.
    pub const CHAINS: u64 = 12;

    /// `iters` rounds of the FMA chains at `width` bits.
    pub unsafe fn fma_loop(width: usize, iters: u64) -> f32 {
        if width == 512 {
            fma512(iters)
        } else {
            fma256(iters)
        }
    }

    macro_rules! fma_kernel {
        ($name:ident, $features:literal, $v:ty, $set1:ident, $fma:ident, $add:ident, $first:ident) => {
            #[target_feature(enable = $features)]
            unsafe fn $name(iters: u64) -> f32 {
                let (a, b) = ($set1(0.999_999), $set1(1e-7));
                let mut acc: [$v; 12] = [$set1(1.0); 12];
                for _ in 0..std::hint::black_box(iters) {
                    for v in acc.iter_mut() {
                        *v = $fma(*v, a, b);
                    }
                }
                let s = acc.iter().fold($set1(0.0), |s, &v| $add(s, v));
                $first(s)
            }
        };
    }
    fma_kernel!(
        fma256,
        "avx2,fma",
        __m256,
        _mm256_set1_ps,
        _mm256_fmadd_ps,
        _mm256_add_ps,
        _mm256_cvtss_f32
    );
    fma_kernel!(
        fma512,
        "avx512f",
        __m512,
        _mm512_set1_ps,
        _mm512_fmadd_ps,
        _mm512_add_ps,
        _mm512_cvtss_f32
    );
}

#[cfg(target_arch = "aarch64")]
mod peak {
    use std::arch::aarch64::*;

    /// Independent FMA chains: enough to cover 4 pipes x 4 cycles.
    pub const CHAINS: u64 = 16;

    /// `iters` rounds of the FMA chains on 128-bit NEON vectors.
    pub unsafe fn fma_loop(_width: usize, iters: u64) -> f32 {
        let (a, b) = (vdupq_n_f32(0.999_999), vdupq_n_f32(1e-7));
        let mut acc = [vdupq_n_f32(1.0); CHAINS as usize];
        for _ in 0..std::hint::black_box(iters) {
            for v in acc.iter_mut() {
                *v = vfmaq_f32(b, *v, a);
            }
        }
        vgetq_lane_f32::<0>(acc.iter().fold(vdupq_n_f32(0.0), |s, &v| vaddq_f32(s, v)))
    }
}

/// Other architectures have no vector level, so `fma_peak` never calls this.
#[cfg(not(any(target_arch = "x86_64", target_arch = "aarch64")))]
mod peak {
    pub const CHAINS: u64 = 0;
    pub unsafe fn fma_loop(_width: usize, _iters: u64) -> f32 {
        0.0
    }
}
