//! Hallucinates a drive: encodes real seed frames, rolls the transition model forward under an
//! action script, and writes what the generator imagines as PNG frames, a contact sheet (seed
//! frames, then every 10th predicted frame) and an animated GIF.
//!
//! ```text
//! cargo run --release --example hallucinate                       # defaults: trained weights, seed clip
//! cargo run --release --example hallucinate -- --steer -0.5 --out left
//! cargo run --release --example hallucinate -- --episodes rec.safetensors --episode 3 --actions plan.csv
//! ```

use clap::Parser;
use drivesim::{Episode, Episodes, Model, Simulator};
use indicatif::{ProgressBar, ProgressStyle};
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

const DEFAULT_WEIGHTS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../weights/default.safetensors");
const DEFAULT_EPISODES: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../weights/seed_clip.safetensors");

#[derive(Parser)]
#[command(about = "Roll the learned driving simulator forward from real frames and write what it dreams")]
struct Args {
    /// drivesim weight file (safetensors; format in weights/README.md)
    #[arg(long, default_value = DEFAULT_WEIGHTS)]
    weights: PathBuf,
    /// Episodes file holding the seed frames and their recorded actions
    #[arg(long, default_value = DEFAULT_EPISODES)]
    episodes: PathBuf,
    /// Which episode of the file to seed from
    #[arg(long, default_value_t = 0)]
    episode: usize,
    /// How many frames from the start of the episode seed the rollout
    #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u32).range(1..))]
    seeds: u32,
    /// Predicted frames to generate
    #[arg(long, default_value_t = 100, value_parser = clap::value_parser!(u32).range(1..=100_000))]
    steps: u32,
    /// Constant steering for every predicted step (default: one slow left-right sine)
    #[arg(long, allow_hyphen_values = true)]
    steer: Option<f32>,
    /// Constant speed for every predicted step (default: the last seed frame's speed)
    #[arg(long, allow_hyphen_values = true)]
    speed: Option<f32>,
    /// CSV with one `speed,steering` line per predicted step, instead of --steer/--speed
    #[arg(long, conflicts_with_all = ["steer", "speed"])]
    actions: Option<PathBuf>,
    /// Output folder
    #[arg(long, default_value = "hallucination")]
    out: PathBuf,
    /// Random seed for --sample
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Seed with codes sampled from the encoder's sigma instead of its mean
    #[arg(long)]
    sample: bool,
}

fn main() -> ExitCode {
    match run(&Args::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(message) => {
            eprintln!("error: {message}");
            ExitCode::FAILURE
        }
    }
}

fn run(args: &Args) -> Result<(), String> {
    let model = Model::load(&args.weights).map_err(|e| format!("weights: {e}"))?;
    let config = *model.config();
    let episodes = Episodes::load(&args.episodes).map_err(|e| format!("episodes: {e}"))?;
    let episode = episodes
        .episode(args.episode)
        .map_err(|e| format!("{}: {e}", args.episodes.display()))?;
    if (episode.height, episode.width, Episodes::CHANNELS) != (config.height, config.width, config.channels) {
        return Err(format!(
            "the weights expect {}x{}x{} frames, {} holds {}x{}x3",
            config.height,
            config.width,
            config.channels,
            args.episodes.display(),
            episode.height,
            episode.width
        ));
    }
    if config.action_dim != Episodes::ACTION_DIM {
        return Err(format!(
            "the weights take {} controls, episodes hold (speed, steering)",
            config.action_dim
        ));
    }
    let seeds = args.seeds as usize;
    if seeds > episode.len() {
        return Err(format!(
            "--seeds {seeds}: episode {} has only {} frames",
            args.episode,
            episode.len()
        ));
    }
    let steps = args.steps as usize;

    // The recorded actions between the seed frames, then the script for the predicted steps.
    let mut actions = episode.actions[..(seeds - 1) * 2].to_vec();
    actions.extend(action_script(args, &episode, seeds, steps)?);

    let mut seed_frames = vec![0.0; seeds * config.frame_len()];
    for (i, frame) in seed_frames.chunks_exact_mut(config.frame_len()).enumerate() {
        episode.frame_f32(i, frame).map_err(|e| e.to_string())?;
    }

    let mut sim = Simulator::new(&model).map_err(|e| e.to_string())?;
    let mut codes = vec![0.0; steps * config.z_dim];
    if args.sample {
        let seed_codes = sample_codes(&mut sim, &seed_frames, args.seed).map_err(|e| e.to_string())?;
        sim.rollout_from_codes(&seed_codes, &actions, &mut codes, None)
    } else {
        sim.rollout(&seed_frames, &actions, &mut codes, None)
    }
    .map_err(|e| e.to_string())?;

    std::fs::create_dir_all(&args.out).map_err(|e| format!("cannot create {}: {e}", args.out.display()))?;
    let (h, w) = (config.height, config.width);
    let mut images: Vec<Vec<u8>> = seed_frames.chunks_exact(config.frame_len()).map(to_rgb).collect();
    let progress = ProgressBar::new(steps as u64)
        .with_style(ProgressStyle::with_template("{bar:40} {pos}/{len} frames ({per_sec})").expect("static template"));
    let mut frame = vec![0.0; config.frame_len()];
    for (t, code) in codes.chunks_exact(config.z_dim).enumerate() {
        sim.generate(code, &mut frame).map_err(|e| e.to_string())?;
        let rgb = to_rgb(&frame);
        write_png(&args.out.join(format!("frame_{t:04}.png")), w, h, &rgb)?;
        images.push(rgb);
        progress.inc(1);
    }
    progress.finish_and_clear();

    // Seed frames, then the frames after 10, 20, ... predicted steps.
    let sheet: Vec<&[u8]> = images[..seeds]
        .iter()
        .chain(images[seeds..].iter().skip(9).step_by(10))
        .map(Vec::as_slice)
        .collect();
    let (sheet_w, sheet_h, sheet_rgb) = contact_sheet(&sheet, w, h, 10);
    write_png(&args.out.join("contact_sheet.png"), sheet_w, sheet_h, &sheet_rgb)?;
    write_gif(&args.out.join("rollout.gif"), w, h, &images)?;
    println!(
        "wrote {steps} frames, contact_sheet.png and rollout.gif to {} ({seeds} seed frames, episode {} of {})",
        args.out.display(),
        args.episode,
        args.episodes.display()
    );
    Ok(())
}

/// `(speed, steering)` for each predicted step.
fn action_script(args: &Args, episode: &Episode<'_>, seeds: usize, steps: usize) -> Result<Vec<f32>, String> {
    if let Some(path) = &args.actions {
        return read_actions_csv(path, steps);
    }
    let recorded_speed = episode.actions[(seeds - 1) * 2];
    let speed = args.speed.unwrap_or(recorded_speed);
    Ok((0..steps)
        .flat_map(|t| {
            let sine = 0.4 * (std::f32::consts::TAU * t as f32 / steps as f32).sin();
            [speed, args.steer.unwrap_or(sine)]
        })
        .collect())
}

fn read_actions_csv(path: &Path, steps: usize) -> Result<Vec<f32>, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("cannot read {}: {e}", path.display()))?;
    let mut actions = Vec::with_capacity(steps * 2);
    for (n, line) in text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()) {
        let values: Result<Vec<f32>, _> = line.split(',').map(|v| v.trim().parse::<f32>()).collect();
        match values {
            Ok(v) if v.len() == 2 && v.iter().all(|x| x.is_finite()) => actions.extend(v),
            _ => {
                return Err(format!(
                    "{}:{}: expected `speed,steering`, found {line:?}",
                    path.display(),
                    n + 1
                ))
            }
        }
    }
    if actions.len() != steps * 2 {
        return Err(format!(
            "{}: {} actions for --steps {steps}",
            path.display(),
            actions.len() / 2
        ));
    }
    Ok(actions)
}

/// Encodes each seed frame and draws `z = mean + exp(logsigma) * noise`.
fn sample_codes(sim: &mut Simulator<'_>, seed_frames: &[f32], seed: u64) -> drivesim::Result<Vec<f32>> {
    let (frame_len, z) = (sim.config().frame_len(), sim.config().z_dim);
    let mut codes = vec![0.0; seed_frames.len() / frame_len * z];
    let mut logsigma = vec![0.0; z];
    let mut noise = Gaussian(seed);
    for (frame, code) in seed_frames.chunks_exact(frame_len).zip(codes.chunks_exact_mut(z)) {
        sim.encode_with_logsigma(frame, code, &mut logsigma)?;
        for (c, s) in code.iter_mut().zip(&logsigma) {
            *c += s.exp() * noise.next();
        }
    }
    Ok(codes)
}

/// Standard normal samples (SplitMix64 and Box-Muller): enough for sampling a code.
struct Gaussian(u64);

impl Gaussian {
    fn uniform(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }

    fn next(&mut self) -> f32 {
        let (u, v) = (self.uniform().max(f64::MIN_POSITIVE), self.uniform());
        ((-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()) as f32
    }
}

/// [-1, 1] HWC floats to RGB bytes.
fn to_rgb(frame: &[f32]) -> Vec<u8> {
    frame
        .iter()
        .map(|v| ((v + 1.0) * 127.5).round().clamp(0.0, 255.0) as u8)
        .collect()
}

/// Tiles frames left to right, `columns` per row, with a 2-pixel white gap.
fn contact_sheet(frames: &[&[u8]], w: usize, h: usize, columns: usize) -> (usize, usize, Vec<u8>) {
    const GAP: usize = 2;
    let columns = columns.min(frames.len()).max(1);
    let rows = frames.len().div_ceil(columns);
    let (sheet_w, sheet_h) = (columns * (w + GAP) + GAP, rows * (h + GAP) + GAP);
    let mut sheet = vec![255u8; sheet_w * sheet_h * 3];
    for (i, frame) in frames.iter().enumerate() {
        let (x0, y0) = (GAP + (i % columns) * (w + GAP), GAP + (i / columns) * (h + GAP));
        for (y, row) in frame.chunks_exact(w * 3).enumerate() {
            let start = ((y0 + y) * sheet_w + x0) * 3;
            sheet[start..start + w * 3].copy_from_slice(row);
        }
    }
    (sheet_w, sheet_h, sheet)
}

fn write_png(path: &Path, w: usize, h: usize, rgb: &[u8]) -> Result<(), String> {
    let fail = |e: &dyn std::fmt::Display| format!("cannot write {}: {e}", path.display());
    let file = File::create(path).map_err(|e| fail(&e))?;
    let mut encoder = png::Encoder::new(BufWriter::new(file), w as u32, h as u32);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    encoder
        .write_header()
        .and_then(|mut writer| writer.write_image_data(rgb))
        .map_err(|e| fail(&e))
}

/// An endless GIF at 10 frames per second, each frame shown twice as large.
fn write_gif(path: &Path, w: usize, h: usize, frames: &[Vec<u8>]) -> Result<(), String> {
    let fail = |e: &dyn std::fmt::Display| format!("cannot write {}: {e}", path.display());
    let file = File::create(path).map_err(|e| fail(&e))?;
    let (gw, gh) = (2 * w as u16, 2 * h as u16);
    let mut encoder = gif::Encoder::new(BufWriter::new(file), gw, gh, &[]).map_err(|e| fail(&e))?;
    encoder.set_repeat(gif::Repeat::Infinite).map_err(|e| fail(&e))?;
    for rgb in frames {
        let doubled: Vec<u8> = (0..2 * h)
            .flat_map(|y| (0..2 * w).flat_map(move |x| rgb[((y / 2) * w + x / 2) * 3..][..3].to_vec()))
            .collect();
        let mut frame = gif::Frame::from_rgb_speed(gw, gh, &doubled, 10);
        frame.delay = 10; // hundredths of a second
        encoder.write_frame(&frame).map_err(|e| fail(&e))?;
    }
    Ok(())
}
