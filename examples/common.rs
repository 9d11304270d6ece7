//! What several examples share: the model and seed arguments, encoding episodes, progress bars,
//! PNG files, error reports.
#![allow(dead_code)] // each example uses part of it

use drivesim::{Episodes, Model, Simulator};
use indicatif::{ProgressBar, ProgressStyle};
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// The weights and the episode whose first frames seed a drive: the arguments of every example
/// that dreams from real frames (`#[command(flatten)]`).
#[derive(clap::Args)]
pub struct SeedArgs {
    /// drivesim weight file (safetensors; format in weights/README.md)
    #[arg(long, default_value_os_t = in_repository("weights/default.safetensors"))]
    pub weights: PathBuf,
    /// Episodes file holding the seed frames and their recorded actions
    #[arg(long, default_value_os_t = in_repository("weights/seed_clip.safetensors"))]
    pub episodes: PathBuf,
    /// Which episode of the file to seed from
    #[arg(long, default_value_t = 0)]
    pub episode: usize,
}

/// One episode's encoded frames and its actions.
pub struct Encoded {
    /// `[frames, z]`: the encoder's means.
    pub codes: Vec<f32>,
    /// `[frames, 2]`: (speed, steering) after each frame.
    pub actions: Vec<f32>,
    /// `[frames, 2]`, where the episodes have them: a teacher's (speed, steering) for each frame.
    pub labels: Option<Vec<f32>>,
    /// `[frames]` each, where the episodes have them: the env's reward for each frame's
    /// decision, and 1 where a wheel was on the road (the same in a mirror).
    pub outcomes: Option<(Vec<f32>, Vec<u8>)>,
}

/// Encodes every frame of every episode in `episodes` (batches of 32, `threads` threads).
pub fn encode(model: &Model, episodes: &Episodes, threads: usize, what: &str) -> Result<Vec<Encoded>, String> {
    encode_view(model, episodes, threads, what, false)
}

/// [`encode`], of the episodes as they are or (`mirrored`) seen in a mirror: every frame
/// flipped left to right and the steering (the second action) negated, as a drive on the
/// mirror image of the track would be.
pub fn encode_view(
    model: &Model,
    episodes: &Episodes,
    threads: usize,
    what: &str,
    mirrored: bool,
) -> Result<Vec<Encoded>, String> {
    let c = model.config();
    let (height, width) = episodes.frame_size();
    if (height, width) != (c.height, c.width) || c.action_dim != Episodes::ACTION_DIM {
        return Err(format!(
            "{what}: {height}x{width} frames with 2 actions, the model takes {}x{} with {}",
            c.height, c.width, c.action_dim
        ));
    }
    const BATCH: usize = 32;
    let mut sim = Simulator::with_batch(model, BATCH)
        .and_then(|s| s.with_threads(threads))
        .map_err(|e| e.to_string())?;
    let total: usize = (0..episodes.len())
        .map(|i| episodes.episode(i).map_or(0, |e| e.len()))
        .sum();
    let progress = bar(
        total as u64,
        &format!("encoding {what}: {{pos}}/{{len}} frames ({{per_sec}}, {{eta}} left)"),
    );
    let mut frames = vec![0.0; BATCH * c.frame_len()];
    let mut out = Vec::with_capacity(episodes.len());
    for i in 0..episodes.len() {
        let episode = episodes.episode(i).map_err(|e| e.to_string())?;
        let mut codes = vec![0.0; episode.len() * c.z_dim];
        for start in (0..episode.len()).step_by(BATCH) {
            let n = BATCH.min(episode.len() - start);
            for (j, frame) in frames.chunks_exact_mut(c.frame_len()).take(n).enumerate() {
                episode.frame_f32(start + j, frame).map_err(|e| e.to_string())?;
                if mirrored {
                    mirror(frame, c.width, c.channels);
                }
            }
            let z = &mut codes[start * c.z_dim..][..n * c.z_dim];
            sim.encode(&frames[..n * c.frame_len()], z).map_err(|e| e.to_string())?;
            progress.inc(n as u64);
        }
        let mut actions = episode.actions.to_vec();
        let mut labels = episode.labels.map(<[f32]>::to_vec);
        if mirrored {
            for pairs in core::iter::once(&mut actions).chain(labels.as_mut()) {
                pairs
                    .iter_mut()
                    .skip(1)
                    .step_by(2)
                    .for_each(|steering| *steering = -*steering);
            }
        }
        let outcomes = episode
            .rewards
            .zip(episode.on_road)
            .map(|(r, o)| (r.to_vec(), o.to_vec()));
        out.push(Encoded {
            codes,
            actions,
            labels,
            outcomes,
        });
    }
    progress.finish_and_clear();
    Ok(out)
}

/// An HWC frame `width` pixels wide, of `channels` values each, flipped left to right in place.
pub fn mirror(frame: &mut [f32], width: usize, channels: usize) {
    for row in frame.chunks_exact_mut(width * channels) {
        for i in 0..width / 2 {
            for k in 0..channels {
                row.swap(i * channels + k, (width - 1 - i) * channels + k);
            }
        }
    }
}

/// A progress bar drawn with `template` (indicatif's syntax).
pub fn bar(len: u64, template: &str) -> ProgressBar {
    ProgressBar::new(len).with_style(ProgressStyle::with_template(template).expect("static template"))
}

/// Writes an 8-bit RGB image.
pub fn write_png(path: &Path, w: usize, h: usize, rgb: &[u8]) -> Result<(), String> {
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

/// An error and its sources, one after another ("cannot read `w.safetensors`: No such file").
pub fn report(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        text = format!("{text}: {s}");
        source = s.source();
    }
    text
}

/// An example's exit: success, or the message on standard error and failure.
pub fn exit(result: Result<(), String>) -> ExitCode {
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(message) => {
            eprintln!("error: {message}");
            ExitCode::FAILURE
        }
    }
}

/// Seeded standard normal samples (SplitMix64 and Box-Muller), and uniform ones in [0, 1).
pub struct Gaussian(pub u64);

impl Gaussian {
    pub fn uniform(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }

    pub fn next(&mut self) -> f32 {
        let (u, v) = (self.uniform().max(f64::MIN_POSITIVE), self.uniform());
        ((-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()) as f32
    }
}

/// An endless GIF at the model's frame rate, each frame shown twice as large, written frame by
/// frame.
pub struct Gif {
    encoder: gif::Encoder<BufWriter<File>>,
    /// Hundredths of a second per frame.
    delay: u16,
    path: PathBuf,
    w: usize,
    h: usize,
    doubled: Vec<u8>,
}

impl Gif {
    /// A GIF of `w x h` frames (drawn at twice the size) played at `frame_hz` frames per second
    /// (the model's, so that it plays in real time), 10 without one.
    pub fn create(path: &Path, w: usize, h: usize, frame_hz: Option<f32>) -> Result<Gif, String> {
        let fail = |e: &dyn std::fmt::Display| format!("cannot write {}: {e}", path.display());
        let file = File::create(path).map_err(|e| fail(&e))?;
        let mut encoder =
            gif::Encoder::new(BufWriter::new(file), 2 * w as u16, 2 * h as u16, &[]).map_err(|e| fail(&e))?;
        encoder.set_repeat(gif::Repeat::Infinite).map_err(|e| fail(&e))?;
        // GIF delays are whole hundredths of a second; browsers play delays under 2 slowly.
        let delay = frame_hz.map_or(10.0, |hz| (100.0 / hz).round()).clamp(2.0, 100.0) as u16;
        Ok(Gif {
            encoder,
            delay,
            path: path.to_path_buf(),
            w,
            h,
            doubled: vec![0; 4 * w * h * 3],
        })
    }

    pub fn push(&mut self, rgb: &[u8]) -> Result<(), String> {
        let (w, h) = (self.w, self.h);
        for (y, line) in self.doubled.chunks_exact_mut(2 * w * 3).enumerate() {
            for (x, pixel) in line.chunks_exact_mut(3).enumerate() {
                pixel.copy_from_slice(&rgb[((y / 2) * w + x / 2) * 3..][..3]);
            }
        }
        let mut frame = gif::Frame::from_rgb_speed(2 * w as u16, 2 * h as u16, &self.doubled, 10);
        frame.delay = self.delay;
        self.encoder
            .write_frame(&frame)
            .map_err(|e| format!("cannot write {}: {e}", self.path.display()))
    }
}

/// `path` inside this repository (the examples' parent folder), so that the defaults work from
/// any directory.
pub fn in_repository(path: &str) -> PathBuf {
    let examples = Path::new(env!("CARGO_MANIFEST_DIR"));
    examples.parent().unwrap_or(examples).join(path)
}
