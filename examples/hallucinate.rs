//! Hallucinates a drive: encodes real seed frames, rolls the transition model forward under an
//! action script, and writes what the generator imagines as PNG frames, a labelled contact
//! sheet (a row of seed frames, then rows of predicted frames evenly spaced to the last step)
//! and an animated GIF.
//!
//! ```text
//! cargo run --release --example hallucinate                       # defaults: trained weights, seed clip
//! cargo run --release --example hallucinate -- --steer -0.5 --out left
//! cargo run --release --example hallucinate -- --episodes rec.safetensors --episode 3 --actions plan.csv
//! ```
//!
//! Every frame goes to disk as it is generated (its PNG and its GIF frame), so memory stays
//! flat however many steps are asked for.

#[path = "common.rs"]
mod common;

use clap::Parser;
use common::{report, write_png, Gaussian, Gif, SeedArgs};
use drivesim::{frames_to_rgb, Episode, Episodes, Model, PixelLayout, Simulator};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// Predicted steps when neither --steps nor --actions says.
const DEFAULT_STEPS: usize = 100;

#[derive(Parser)]
#[command(about = "Roll the learned driving simulator forward from real frames and write what it dreams")]
struct Args {
    #[command(flatten)]
    source: SeedArgs,
    /// How many frames from the start of the episode seed the rollout
    #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u32).range(1..))]
    seeds: u32,
    /// Predicted frames to generate [default: one per line of --actions, else 100]
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=100_000))]
    steps: Option<u32>,
    /// Constant steering for every predicted step (default: one slow left-right sine)
    #[arg(long, allow_hyphen_values = true)]
    steer: Option<f32>,
    /// Constant speed for every predicted step (default: the last seed frame's speed)
    #[arg(long, allow_hyphen_values = true)]
    speed: Option<f32>,
    /// CSV with one `speed,steering` line per predicted step, instead of --steer/--speed
    /// (an optional `speed,steering` header line and `#` comments are skipped)
    #[arg(long, conflicts_with_all = ["steer", "speed"])]
    actions: Option<PathBuf>,
    /// Output folder
    #[arg(long, default_value = "hallucination")]
    out: PathBuf,
    /// At most this many frames (seed frames included) go into rollout.gif, at the model's
    /// frame rate (`drivesim.frame_hz`; 10 per second without it); 0 writes no GIF
    #[arg(long, default_value_t = 300)]
    gif_frames: usize,
    /// Random seed for --sample
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Seed with codes sampled from the encoder's sigma instead of its mean
    #[arg(long)]
    sample: bool,
}

fn main() -> ExitCode {
    common::exit(run(&Args::parse()))
}

fn run(args: &Args) -> Result<(), String> {
    let model = Model::load(&args.source.weights).map_err(|e| format!("weights: {}", report(&e)))?;
    let config = *model.config();
    let episodes = Episodes::load(&args.source.episodes).map_err(|e| format!("episodes: {}", report(&e)))?;
    let episode = episodes
        .episode(args.source.episode)
        .map_err(|e| format!("{}: {e}", args.source.episodes.display()))?;
    if (episode.height, episode.width, Episodes::CHANNELS) != (config.height, config.width, config.channels) {
        return Err(format!(
            "the weights expect {}x{}x{} frames, {} holds {}x{}x3",
            config.height,
            config.width,
            config.channels,
            args.source.episodes.display(),
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
            args.source.episode,
            episode.len()
        ));
    }

    // The recorded actions between the seed frames, then the script for the predicted steps.
    let script = action_script(args, &episode, seeds)?;
    if let Err(e) = model.check_actions(&script) {
        eprintln!("warning: {e}: the prediction is an extrapolation");
    }
    let steps = script.len() / 2;
    let mut actions = episode.actions[..(seeds - 1) * 2].to_vec();
    actions.extend(script);

    let (h, w, frame_len) = (config.height, config.width, config.frame_len());
    let mut seed_frames = vec![0.0; seeds * frame_len];
    for (i, frame) in seed_frames.chunks_exact_mut(frame_len).enumerate() {
        episode.frame_f32(i, frame).map_err(|e| e.to_string())?;
    }
    let seed_rgb = |i: usize| &episode.frames[i * frame_len..][..frame_len];

    let mut sim = Simulator::new(&model).map_err(|e| e.to_string())?;
    let seed_codes = seed_codes(&mut sim, &seed_frames, args.sample.then_some(args.seed)).map_err(|e| e.to_string())?;
    drop(seed_frames);

    std::fs::create_dir_all(&args.out).map_err(|e| format!("cannot create {}: {e}", args.out.display()))?;
    let sheet = SheetPlan::new(seeds, steps);
    let mut sheet_frames: Vec<Vec<u8>> = (seeds - sheet.seeds_shown..seeds)
        .map(|i| seed_rgb(i).to_vec())
        .collect();
    let gif_path = args.out.join("rollout.gif");
    let gif_frames = args.gif_frames.min(seeds + steps);
    let mut gif = match gif_frames {
        0 => None,
        _ => Some(Gif::create(&gif_path, w, h, model.frame_hz())?),
    };
    if let Some(gif) = gif.as_mut() {
        for i in 0..seeds.min(gif_frames) {
            gif.push(seed_rgb(i))?;
        }
    }

    // The same steps as `Simulator::rollout`, one at a time so that each frame is written as
    // soon as it exists: teacher-forced through the seeds, then fed its own predictions.
    let digits = steps.ilog10() as usize + 1;
    // frame_0001.png is the first predicted frame: t = 1 on the contact sheet, the last seed t = 0.
    let name = |t: usize| format!("frame_{t:0width$}.png", width = digits.max(4));
    let progress = ProgressBar::new(steps as u64).with_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} frames: PNG, GIF ({per_sec}, {eta} left)")
            .expect("static template"),
    );
    let (mut hidden, mut z) = (vec![0.0; config.hidden_dim], vec![0.0; config.z_dim]);
    for (code, action) in seed_codes.chunks_exact(config.z_dim).zip(actions.chunks_exact(2)) {
        sim.transition(code, &mut hidden, action, &mut z)
            .map_err(|e| e.to_string())?;
    }
    let mut frame = vec![0.0; frame_len];
    let mut rgb = vec![0u8; frame_len];
    for t in 0..steps {
        if t > 0 {
            let action = &actions[(seeds - 1 + t) * 2..][..2];
            sim.transition_fed_back(&mut hidden, action, &mut z)
                .map_err(|e| e.to_string())?;
        }
        sim.generate(&z, &mut frame).map_err(|e| e.to_string())?;
        frames_to_rgb(&frame, PixelLayout::Hwc, &config, &mut rgb).map_err(|e| e.to_string())?;
        write_png(&args.out.join(name(t + 1)), w, h, &rgb)?;
        if let Some(gif) = gif.as_mut().filter(|_| seeds + t < gif_frames) {
            gif.push(&rgb)?;
        }
        if sheet.predicted.binary_search(&(t + 1)).is_ok() {
            sheet_frames.push(rgb.clone());
        }
        progress.inc(1);
    }
    progress.finish_and_clear();

    let (sheet_w, sheet_h, sheet_rgb) = sheet.draw(&sheet_frames, w, h);
    write_png(&args.out.join("contact_sheet.png"), sheet_w, sheet_h, &sheet_rgb)?;
    println!(
        "wrote {steps} predicted frames ({} .. {}) and contact_sheet.png to {} ({seeds} seed frame{} from episode {} of {})",
        name(1),
        name(steps),
        args.out.display(),
        if seeds == 1 { "" } else { "s" },
        args.source.episode,
        args.source.episodes.display()
    );
    match gif_frames {
        0 => println!("no rollout.gif (--gif-frames 0)"),
        n if n < seeds + steps => println!(
            "rollout.gif holds the first {n} of the {} frames ({seeds} seed, {steps} predicted); --gif-frames raises the limit",
            seeds + steps
        ),
        n => println!("rollout.gif: {n} frames ({seeds} seed, {steps} predicted)"),
    }
    if args.out.join(name(steps + 1)).exists() {
        println!(
            "note: {} still holds frames of a longer earlier run (from {} on)",
            args.out.display(),
            name(steps + 1)
        );
    }
    Ok(())
}

/// `(speed, steering)` for each predicted step.
fn action_script(args: &Args, episode: &Episode<'_>, seeds: usize) -> Result<Vec<f32>, String> {
    if let Some(path) = &args.actions {
        let mut actions = read_actions_csv(path)?;
        let lines = actions.len() / 2;
        match args.steps.map(|s| s as usize) {
            Some(steps) if steps > lines => {
                return Err(format!(
                    "--steps {steps}, but {} has {lines} actions (leave --steps out to take the file's length)",
                    path.display()
                ))
            }
            Some(steps) => actions.truncate(steps * 2),
            None => {}
        }
        return Ok(actions);
    }
    let steps = args.steps.map_or(DEFAULT_STEPS, |s| s as usize);
    let recorded_speed = episode.actions[(seeds - 1) * 2];
    let speed = args.speed.unwrap_or(recorded_speed);
    Ok((0..steps)
        .flat_map(|t| {
            let sine = 0.4 * (std::f32::consts::TAU * t as f32 / steps as f32).sin();
            [speed, args.steer.unwrap_or(sine)]
        })
        .collect())
}

/// One `speed,steering` line per step; blank lines, `#` comments and a header line are skipped.
fn read_actions_csv(path: &Path) -> Result<Vec<f32>, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("cannot read {}: {e}", path.display()))?;
    let mut actions = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        let header = actions.is_empty() && line.replace(' ', "").eq_ignore_ascii_case("speed,steering");
        if line.is_empty() || line.starts_with('#') || header {
            continue;
        }
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
    if actions.is_empty() {
        return Err(format!("{}: no `speed,steering` lines", path.display()));
    }
    if actions.len() / 2 > 100_000 {
        return Err(format!(
            "{}: {} actions, at most 100000 steps",
            path.display(),
            actions.len() / 2
        ));
    }
    Ok(actions)
}

/// Encodes each seed frame: its mean code, or with `sample = Some(seed)` a code drawn as
/// `z = mean + exp(logsigma) * noise`.
fn seed_codes(sim: &mut Simulator<&Model>, seed_frames: &[f32], sample: Option<u64>) -> drivesim::Result<Vec<f32>> {
    let (frame_len, z) = (sim.config().frame_len(), sim.config().z_dim);
    let mut codes = vec![0.0; seed_frames.len() / frame_len * z];
    let mut logsigma = vec![0.0; z];
    let mut noise = sample.map(Gaussian);
    for (frame, code) in seed_frames.chunks_exact(frame_len).zip(codes.chunks_exact_mut(z)) {
        sim.encode_with_logsigma(frame, code, &mut logsigma)?;
        if let Some(noise) = noise.as_mut() {
            for (c, s) in code.iter_mut().zip(&logsigma) {
                *c += s.exp() * noise.next();
            }
        }
    }
    Ok(codes)
}

/// Which frames the contact sheet shows: a row of the last seed frames, then rows of predicted
/// frames at steps spread evenly up to the last one. The predicted rows are full; the seed row
/// is too unless there are fewer seed frames than columns (then it is shorter: no blank cells).
struct SheetPlan {
    /// At most 10, at most `steps`, at least 5 where there are 5 steps.
    columns: usize,
    /// The last `seeds_shown` seed frames form the first row.
    seeds_shown: usize,
    /// 1-based step numbers, increasing, `columns * rows` of them, the last one `steps`.
    predicted: Vec<usize>,
}

impl SheetPlan {
    /// About 10 predicted frames: every 10th of 100 steps, every 3rd of 30.
    const TARGET: usize = 10;
    const GAP: usize = 2;
    const BAND: usize = FONT_H + 4;
    const LABEL_W: usize = 9 * (FONT_W + 1) + 6; // "PREDICTED"
    const BACKGROUND: [u8; 3] = [40, 40, 40];
    const SEED_INK: [u8; 3] = [130, 200, 255];
    const PREDICTED_INK: [u8; 3] = [255, 200, 100];

    fn new(seeds: usize, steps: usize) -> SheetPlan {
        let columns = seeds.clamp(5, Self::TARGET).min(steps);
        let rows = (steps / columns).min(Self::TARGET.div_ceil(columns)).max(1);
        let n = columns * rows;
        // Rounded i * steps / n: distinct (steps >= n), ending at `steps`.
        let predicted = (1..=n).map(|i| (2 * i * steps + n) / (2 * n)).collect();
        SheetPlan {
            columns,
            seeds_shown: seeds.min(columns),
            predicted,
        }
    }

    /// Draws the sheet from the shown seed frames then the predicted frames, in the plan's
    /// order. Each row is labelled SEED or PREDICTED on the left, each frame with its step above
    /// it (the last seed frame is t=0).
    fn draw(&self, frames: &[Vec<u8>], w: usize, h: usize) -> (usize, usize, Vec<u8>) {
        assert_eq!(frames.len(), self.seeds_shown + self.predicted.len());
        let (gap, band) = (Self::GAP, Self::BAND);
        let rows = 1 + self.predicted.len() / self.columns;
        let (sheet_w, sheet_h) = (Self::LABEL_W + self.columns * (w + gap), gap + rows * (band + h + gap));
        let mut sheet: Vec<u8> = Self::BACKGROUND.repeat(sheet_w * sheet_h);
        let seeds = (1 - self.seeds_shown as i64..=0).enumerate();
        let seeds = seeds.map(|(column, t)| (0, column, t, "SEED", Self::SEED_INK));
        let predicted = self.predicted.iter().enumerate().map(|(i, &t)| {
            let (row, column) = (1 + i / self.columns, i % self.columns);
            (row, column, t as i64, "PREDICTED", Self::PREDICTED_INK)
        });
        for ((row, column, t, label, ink), frame) in seeds.chain(predicted).zip(frames) {
            let (x0, y0) = (Self::LABEL_W + column * (w + gap), gap + row * (band + h + gap));
            if column == 0 {
                let y = y0 + band + h.saturating_sub(FONT_H) / 2;
                draw_text(&mut sheet, sheet_w, 3, y, label, ink);
            }
            draw_text(&mut sheet, sheet_w, x0 + 2, y0 + 2, &format!("t={t}"), ink);
            for (y, line) in frame.chunks_exact(w * 3).enumerate() {
                let start = ((y0 + band + y) * sheet_w + x0) * 3;
                sheet[start..start + w * 3].copy_from_slice(line);
            }
        }
        (sheet_w, sheet_h, sheet)
    }
}

const FONT_W: usize = 5;
const FONT_H: usize = 7;

/// A 5x7 pixel font for the labels: one byte per row, the low five bits left to right.
fn glyph(c: char) -> [u8; FONT_H] {
    match c {
        '0' => [0x0E, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0E],
        '1' => [0x04, 0x0C, 0x04, 0x04, 0x04, 0x04, 0x0E],
        '2' => [0x0E, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1F],
        '3' => [0x1F, 0x02, 0x04, 0x02, 0x01, 0x11, 0x0E],
        '4' => [0x02, 0x06, 0x0A, 0x12, 0x1F, 0x02, 0x02],
        '5' => [0x1F, 0x10, 0x1E, 0x01, 0x01, 0x11, 0x0E],
        '6' => [0x06, 0x08, 0x10, 0x1E, 0x11, 0x11, 0x0E],
        '7' => [0x1F, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08],
        '8' => [0x0E, 0x11, 0x11, 0x0E, 0x11, 0x11, 0x0E],
        '9' => [0x0E, 0x11, 0x11, 0x0F, 0x01, 0x02, 0x0C],
        'C' => [0x0E, 0x11, 0x10, 0x10, 0x10, 0x11, 0x0E],
        'D' => [0x1E, 0x11, 0x11, 0x11, 0x11, 0x11, 0x1E],
        'E' => [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x1F],
        'I' => [0x0E, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0E],
        'P' => [0x1E, 0x11, 0x11, 0x1E, 0x10, 0x10, 0x10],
        'R' => [0x1E, 0x11, 0x11, 0x1E, 0x14, 0x12, 0x11],
        'S' => [0x0F, 0x10, 0x10, 0x0E, 0x01, 0x01, 0x1E],
        'T' => [0x1F, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04],
        't' => [0x08, 0x08, 0x1C, 0x08, 0x08, 0x09, 0x06],
        '=' => [0x00, 0x00, 0x1F, 0x00, 0x1F, 0x00, 0x00],
        '-' => [0x00, 0x00, 0x00, 0x1F, 0x00, 0x00, 0x00],
        _ => [0; FONT_H],
    }
}

/// Draws `text` with its top left corner at (x, y), one pixel between characters.
fn draw_text(rgb: &mut [u8], width: usize, x: usize, y: usize, text: &str, ink: [u8; 3]) {
    for (i, c) in text.chars().enumerate() {
        for (dy, bits) in glyph(c).into_iter().enumerate() {
            for dx in 0..FONT_W {
                if bits & (0x10 >> dx) != 0 {
                    let at = ((y + dy) * width + x + i * (FONT_W + 1) + dx) * 3;
                    rgb[at..at + 3].copy_from_slice(&ink);
                }
            }
        }
    }
}
