//! Drives inside the dream: seeds an `Environment` with real frames, then closes the loop for
//! `--steps` steps with no real frame, a planner choosing the steering at every step, and
//! compares it with open-loop constant and random steering.
//!
//! ```text
//! cargo run --release --example drive -- [--steps 500] [--out drive] [--candidates 64]
//!     [--horizon 10] [--iterations 3] [--threads 1] [--weights W] [--episodes E --episode N]
//! ```
//! - **What the road looks like**: in a band of rows just ahead of the car (the car sits at the
//!   bottom centre of the model's view), grey road pixels against green grass. A frame is "on
//!   the road" when road covers the middle of the band, and its offset is the road's centre in
//!   the band minus the car's column, in pixels.
//! - **A cost on codes, learned from frames**: generating frames for every candidate would cost
//!   a generator pass each, so the example first rolls the model out under random steering,
//!   measures the offset on the generated frames and fits a linear map from codes to offsets
//!   (ridge least squares). Planning then needs codes only.
//! - **The planner**: the cross-entropy method over steering sequences of `--horizon` steps at
//!   the seed's speed; each iteration rolls `--candidates` sequences out at once
//!   (`Environment::rollout_candidates`), keeps the eighth with the lowest squared predicted
//!   offset (plus a little for steering changes) and refits a Gaussian. The first action of the
//!   mean is applied; the rest seeds the next step's plan.
//!
//! Writes the planner's frames as `frame_NNNN.png`, a contact sheet and `drive.gif` (the first
//! 300 frames) into `--out`. Plans are checked against the model's `drivesim.actions`.

#[path = "common.rs"]
mod common;

use clap::Parser;
use common::{report, write_png, Gaussian, Gif, SeedArgs};
use drivesim::{frames_to_rgb, Config, Environment, Episodes, Model, PixelLayout};
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

#[derive(Parser)]
#[command(about = "Drive inside the simulator with a planner, against constant and random steering")]
struct Args {
    #[command(flatten)]
    source: SeedArgs,
    #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u32).range(1..=100))]
    seeds: u32,
    #[arg(long, default_value_t = 500, value_parser = clap::value_parser!(u32).range(1..=100_000))]
    steps: u32,
    #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u32).range(8..=4096))]
    candidates: u32,
    #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u32).range(1..=200))]
    horizon: u32,
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..=20))]
    iterations: u32,
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=256))]
    threads: u32,
    #[arg(long, default_value = "drive")]
    out: PathBuf,
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

fn main() -> ExitCode {
    common::exit(run(&Args::parse()))
}

/// Road under and ahead of the car in one 8-bit frame: whether road covers the car's columns
/// in the band, and the road's centre in the band minus the car's column (pixels), if any.
fn road(rgb: &[u8], c: &Config) -> (bool, Option<f32>) {
    let (h, w) = (c.height, c.width);
    let (car, rows) = (w / 2, h * 6 / 10..h * 3 / 4);
    let (mut sum, mut count, mut under) = (0usize, 0usize, 0usize);
    for y in rows.clone() {
        for x in 0..w {
            let p = &rgb[(y * w + x) * 3..][..3];
            let (lo, hi) = (
                p.iter().min().copied().unwrap_or(0),
                p.iter().max().copied().unwrap_or(0),
            );
            // Grey: the channels agree; grass is far greener than red or blue.
            if hi - lo < 25 && hi < 170 && hi > 60 {
                sum += x;
                count += 1;
                under += usize::from(x.abs_diff(car) < 4);
            }
        }
    }
    let on_road = under * 2 > 8 * rows.len();
    (on_road, (count > 0).then(|| sum as f32 / count as f32 - car as f32))
}

/// `offset ≈ w · z + b`, by ridge least squares.
struct OffsetModel {
    w: Vec<f64>,
    b: f64,
}

impl OffsetModel {
    /// Fits on `(code, offset)` samples: the normal equations with a small ridge, solved by
    /// Gaussian elimination (z_dim + 1 unknowns).
    fn fit(codes: &[Vec<f32>], offsets: &[f32]) -> OffsetModel {
        let n = codes[0].len() + 1;
        let mut a = vec![vec![0.0f64; n + 1]; n];
        for (z, &y) in codes.iter().zip(offsets) {
            let x: Vec<f64> = z.iter().map(|&v| v as f64).chain([1.0]).collect();
            for i in 0..n {
                for j in 0..n {
                    a[i][j] += x[i] * x[j];
                }
                a[i][n] += x[i] * y as f64;
            }
        }
        for (i, row) in a.iter_mut().enumerate().take(n - 1) {
            row[i] += 1e-2 * codes.len() as f64;
        }
        for col in 0..n {
            let pivot = (col..n)
                .max_by(|&p, &q| a[p][col].abs().total_cmp(&a[q][col].abs()))
                .unwrap_or(col);
            a.swap(col, pivot);
            let pivot = a[col].clone();
            if pivot[col] == 0.0 {
                continue;
            }
            for (r, row) in a.iter_mut().enumerate() {
                if r != col {
                    let f = row[col] / pivot[col];
                    row[col..].iter_mut().zip(&pivot[col..]).for_each(|(x, p)| *x -= f * p);
                }
            }
        }
        let x: Vec<f64> = (0..n)
            .map(|i| if a[i][i] != 0.0 { a[i][n] / a[i][i] } else { 0.0 })
            .collect();
        OffsetModel {
            w: x[..n - 1].to_vec(),
            b: x[n - 1],
        }
    }

    fn predict(&self, z: &[f32]) -> f64 {
        self.b + self.w.iter().zip(z).map(|(w, &z)| w * z as f64).sum::<f64>()
    }
}

/// How steering is chosen in a run.
#[derive(Clone, Copy, PartialEq)]
enum Driver {
    Planner,
    Constant,
    Random,
}

/// A run's figures: steps on the road, mean |offset| where road was seen, time per step.
struct Figures {
    on_road: usize,
    offset: f64,
    offsets: usize,
    seconds: f64,
}

fn run(args: &Args) -> Result<(), String> {
    let model = Model::load(&args.source.weights).map_err(|e| format!("weights: {}", report(&e)))?;
    let c = *model.config();
    let episodes = Episodes::load(&args.source.episodes).map_err(|e| format!("episodes: {}", report(&e)))?;
    let episode = episodes.episode(args.source.episode).map_err(|e| e.to_string())?;
    let seeds = args.seeds as usize;
    if episode.len() < seeds || (episode.height, episode.width) != (c.height, c.width) {
        return Err(format!(
            "episode {} lacks {seeds} frames of {}x{}",
            args.source.episode, c.height, c.width
        ));
    }
    let mut seed_frames = vec![0.0; seeds * c.frame_len()];
    for (i, f) in seed_frames.chunks_exact_mut(c.frame_len()).enumerate() {
        episode.frame_f32(i, f).map_err(|e| e.to_string())?;
    }
    let seed_actions = &episode.actions[..(seeds - 1) * 2];
    let speed = episode.actions[(seeds - 1) * 2];
    if let Err(e) = model.check_actions(&[speed, -1.0, speed, 1.0]) {
        eprintln!("warning: {e}: the plans are an extrapolation");
    }
    let (candidates, horizon) = (args.candidates as usize, args.horizon as usize);
    let mut env = Environment::new(&model, 8, candidates)
        .and_then(|e| e.with_threads(args.threads as usize))
        .map_err(|e| e.to_string())?;

    // 1. The cost: offsets measured on frames of 8 drives under random steering.
    let (codes, offsets) = samples(&mut env, &c, &seed_frames, seed_actions, speed, args.seed)?;
    let split = codes.len() * 4 / 5;
    let cost = OffsetModel::fit(&codes[..split], &offsets[..split]);
    let held: Vec<(f64, f64)> = codes[split..]
        .iter()
        .zip(&offsets[split..])
        .map(|(z, &o)| (cost.predict(z), o as f64))
        .collect();
    let mean = held.iter().map(|h| h.1).sum::<f64>() / held.len().max(1) as f64;
    let (res, tot) = held.iter().fold((0.0, 0.0), |(r, t), (p, o)| {
        (r + (p - o).powi(2), t + (o - mean).powi(2))
    });
    println!(
        "offset from codes: fitted on {split} generated frames, R² {:.2} on {} others",
        1.0 - res / tot.max(1e-9),
        held.len()
    );

    // 2. The three drivers, each from the same seeds.
    std::fs::create_dir_all(&args.out).map_err(|e| format!("cannot create {}: {e}", args.out.display()))?;
    let mut table = Vec::new();
    for driver in [Driver::Planner, Driver::Constant, Driver::Random] {
        let figures = drive(&mut env, &c, &cost, args, (&seed_frames, seed_actions, speed), driver)?;
        table.push((driver, figures));
    }
    let steps = args.steps as usize;
    println!(
        "{steps} steps after {seeds} seed frames, speed {speed:.1}, {} thread(s):",
        args.threads
    );
    println!("  driver            on road   mean |offset| px   ms per step");
    for (driver, f) in table {
        let name = match driver {
            Driver::Planner => format!("planner ({candidates}x{horizon}, {} it.)", args.iterations),
            Driver::Constant => "constant steering 0".to_string(),
            Driver::Random => "random steering".to_string(),
        };
        println!(
            "  {name:<24} {:>5.1} %   {:>8.2} ({} frames)   {:>8.2}",
            100.0 * f.on_road as f64 / steps as f64,
            f.offset / f.offsets.max(1) as f64,
            f.offsets,
            1e3 * f.seconds / steps as f64
        );
    }
    println!(
        "planner frames: {}/frame_*.png, contact_sheet.png, drive.gif",
        args.out.display()
    );
    Ok(())
}

/// Resets every one of `drives` drives from the same seed frames and actions.
fn reset(
    env: &mut Environment<&Model>,
    c: &Config,
    seed_frames: &[f32],
    seed_actions: &[f32],
    drives: usize,
) -> Result<(), String> {
    let seeds = seed_frames.len() / c.frame_len();
    // Step-major: every drive's seed s, then seed s + 1.
    let mut frames = Vec::new();
    for s in 0..seeds {
        for _ in 0..drives {
            frames.extend_from_slice(&seed_frames[s * c.frame_len()..][..c.frame_len()]);
        }
    }
    let actions: Vec<f32> = (0..seeds - 1)
        .flat_map(|s| (0..drives).flat_map(move |_| [seed_actions[2 * s], seed_actions[2 * s + 1]]))
        .collect();
    env.reset_from_frames(&frames, &actions).map_err(|e| e.to_string())
}

/// Codes and measured offsets of 8 drives rolled out 150 steps under smooth random steering.
fn samples(
    env: &mut Environment<&Model>,
    c: &Config,
    seed_frames: &[f32],
    seed_actions: &[f32],
    speed: f32,
    seed: u64,
) -> Result<(Vec<Vec<f32>>, Vec<f32>), String> {
    let drives = 8;
    let e = |e: drivesim::Error| e.to_string();
    reset(env, c, seed_frames, seed_actions, drives)?;
    let mut noise = Gaussian(seed ^ 0x5eed);
    let mut steer = vec![0.0f32; drives];
    let (mut out, mut rgb) = (vec![0.0; drives * c.frame_len()], vec![0u8; drives * c.frame_len()]);
    let (mut codes, mut offsets) = (Vec::new(), Vec::new());
    for _ in 0..150 {
        for s in steer.iter_mut() {
            *s = (0.8 * *s + 0.35 * noise.next()).clamp(-1.0, 1.0);
        }
        let step: Vec<f32> = steer.iter().flat_map(|&s| [speed, s]).collect();
        env.step(&step).map_err(e)?;
        env.frames(&mut out).map_err(e)?;
        frames_to_rgb(&out, PixelLayout::Hwc, c, &mut rgb).map_err(e)?;
        for d in 0..drives {
            if let (_, Some(offset)) = road(&rgb[d * c.frame_len()..][..c.frame_len()], c) {
                codes.push(env.codes()[d * c.z_dim..][..c.z_dim].to_vec());
                offsets.push(offset);
            }
        }
    }
    Ok((codes, offsets))
}

/// One closed-loop (planner) or open-loop run from the seeds; the planner's frames are written.
fn drive(
    env: &mut Environment<&Model>,
    c: &Config,
    cost: &OffsetModel,
    args: &Args,
    (seed_frames, seed_actions, speed): (&[f32], &[f32], f32),
    driver: Driver,
) -> Result<Figures, String> {
    let e = |e: drivesim::Error| e.to_string();
    let drives = 8;
    reset(env, c, seed_frames, seed_actions, drives)?;
    let (candidates, horizon) = (args.candidates as usize, args.horizon as usize);
    let mut noise = Gaussian(args.seed);
    let mut mean = vec![0.0f32; horizon];
    let mut plan = vec![0.0f32; horizon * candidates * 2];
    let mut codes = vec![0.0f32; horizon * candidates * c.z_dim];
    let mut steering = vec![0.0f32; candidates * horizon];
    let (mut out, mut rgb) = (vec![0.0; drives * c.frame_len()], vec![0u8; drives * c.frame_len()]);
    let mut sheet = Vec::new();
    // The planner's drive, its first 300 frames.
    let mut gif = match driver {
        Driver::Planner => {
            let hz = env.simulator().model().frame_hz();
            Some(Gif::create(&args.out.join("drive.gif"), c.width, c.height, hz)?)
        }
        _ => None,
    };
    let mut figures = Figures {
        on_road: 0,
        offset: 0.0,
        offsets: 0,
        seconds: 0.0,
    };
    let mut random = 0.0f32;
    for t in 0..args.steps as usize {
        let start = Instant::now();
        let steer = match driver {
            Driver::Constant => 0.0,
            Driver::Random => {
                random = (0.8 * random + 0.35 * noise.next()).clamp(-1.0, 1.0);
                random
            }
            Driver::Planner => {
                let mut sigma = vec![0.5f32; horizon];
                for _ in 0..args.iterations {
                    for (n, seq) in steering.chunks_exact_mut(horizon).enumerate() {
                        for (k, s) in seq.iter_mut().enumerate() {
                            // Candidate 0 keeps the mean itself.
                            let eps = if n == 0 { 0.0 } else { noise.next() };
                            *s = (mean[k] + sigma[k] * eps).clamp(-1.0, 1.0);
                        }
                    }
                    for k in 0..horizon {
                        for n in 0..candidates {
                            plan[(k * candidates + n) * 2..][..2].copy_from_slice(&[speed, steering[n * horizon + k]]);
                        }
                    }
                    env.rollout_candidates(0, candidates, &plan, &mut codes, None)
                        .map_err(e)?;
                    let mut scored: Vec<(f64, usize)> = (0..candidates)
                        .map(|n| {
                            let seq = &steering[n * horizon..][..horizon];
                            let road: f64 = (0..horizon)
                                .map(|k| {
                                    cost.predict(&codes[(k * candidates + n) * c.z_dim..][..c.z_dim])
                                        .powi(2)
                                })
                                .sum();
                            let smooth: f64 = seq.windows(2).map(|p| ((p[1] - p[0]) as f64).powi(2)).sum();
                            (road + 10.0 * smooth, n)
                        })
                        .collect();
                    scored.sort_by(|a, b| a.0.total_cmp(&b.0));
                    let elites = &scored[..candidates / 8];
                    for k in 0..horizon {
                        let values: Vec<f32> = elites.iter().map(|&(_, n)| steering[n * horizon + k]).collect();
                        let m = values.iter().sum::<f32>() / values.len() as f32;
                        let v = values.iter().map(|x| (x - m).powi(2)).sum::<f32>() / values.len() as f32;
                        mean[k] = m;
                        sigma[k] = v.sqrt().max(0.05);
                    }
                }
                let first = mean[0];
                mean.rotate_left(1);
                mean[horizon - 1] = mean[horizon.saturating_sub(2)];
                first
            }
        };
        // Drive 0 is the one measured; the others follow the same steering.
        let step: Vec<f32> = (0..drives).flat_map(|_| [speed, steer]).collect();
        env.step(&step).map_err(e)?;
        figures.seconds += start.elapsed().as_secs_f64();
        env.frames(&mut out).map_err(e)?;
        let frame = &mut rgb[..c.frame_len()];
        frames_to_rgb(&out[..c.frame_len()], PixelLayout::Hwc, c, frame).map_err(e)?;
        let (on_road, offset) = road(frame, c);
        figures.on_road += usize::from(on_road);
        if let Some(o) = offset {
            figures.offset += o.abs() as f64;
            figures.offsets += 1;
        }
        if driver == Driver::Planner {
            write_png(
                &args.out.join(format!("frame_{:04}.png", t + 1)),
                c.width,
                c.height,
                frame,
            )?;
            if let Some(gif) = gif.as_mut().filter(|_| t < 300) {
                gif.push(frame)?;
            }
            if t % (args.steps as usize / 20).max(1) == 0 && sheet.len() < 20 {
                sheet.push(frame.to_vec());
            }
        }
    }
    if driver == Driver::Planner {
        let (cols, rows) = (5, sheet.len().div_ceil(5));
        let (w, h) = (c.width * cols, c.height * rows.max(1));
        let mut image = vec![0u8; w * h * 3];
        for (i, f) in sheet.iter().enumerate() {
            let (ox, oy) = ((i % cols) * c.width, (i / cols) * c.height);
            for y in 0..c.height {
                let row = &f[y * c.width * 3..][..c.width * 3];
                image[((oy + y) * w + ox) * 3..][..c.width * 3].copy_from_slice(row);
            }
        }
        write_png(&args.out.join("contact_sheet.png"), w, h, &image)?;
    }
    Ok(figures)
}
