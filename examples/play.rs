//! Drive the dream yourself: serves a page where the arrow keys steer a car inside the learned
//! simulator, frames pushed to the browser as they are generated.
//!
//! ```text
//! cargo run --release --example play                      # then open http://127.0.0.1:8080/
//! cargo run --release --example play -- --port 8000 --episodes rec.safetensors --episode 3 --threads 2
//! ```
//!
//! The server is std's `TcpListener` with a thread per connection and `tungstenite` for the
//! WebSocket: a blocking, dependency-light server (no async runtime) is enough for a page that
//! one person drives, and each connection owns its simulator, dropped with the connection. `GET
//! /` answers the page (`play.html`, built in); `GET /ws` upgrades to the WebSocket. The page
//! sends text messages: `keys STEER THROTTLE` (each -1, 0 or 1: the arrow keys held),
//! `reset`, `sample`. The server sends one text message first (the model's action ranges and
//! whether it samples), then binary frames: a kind byte (0 a seed frame, 1 the dream), the
//! speed and steering (f32, little-endian), a sampling byte, then the frame's RGB bytes.
//! Anything else from the page ends that connection only.

#[path = "common.rs"]
mod common;

use clap::Parser;
use common::{report, SeedArgs};
use drivesim::{frames_to_rgb, Environment, Episodes, Model, PixelLayout};
use std::io::{ErrorKind, Write};
use std::net::{TcpListener, TcpStream};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tungstenite::{Message, WebSocket};

/// The page, served at `/`.
const PAGE: &str = include_str!("play.html");
/// Frames per second the server aims at (it never sends faster).
const TARGET_FPS: f64 = 25.0;
/// Seed frames a reset encodes.
const SEEDS: usize = 5;
/// How far the steering moves toward a held arrow's side (or back to straight) per frame.
const STEER_RATE: f32 = 0.08;
/// How far the speed moves per frame while up or down is held, in the speed's units.
const SPEED_RATE: f32 = 0.5;

#[derive(Parser)]
#[command(about = "Serve a page where a person drives inside the learned driving simulator")]
struct Args {
    /// Port to listen on
    #[arg(long, default_value_t = 8080)]
    port: u16,
    /// Address to listen on (only this machine unless given)
    #[arg(long, default_value = "127.0.0.1")]
    host: String,
    #[command(flatten)]
    source: SeedArgs,
    /// Threads of each connection's simulator
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=64))]
    threads: u32,
}

/// What every connection starts from.
struct Seed {
    model: Arc<Model>,
    /// `SEEDS` frames in [-1, 1] and the `SEEDS - 1` actions between them.
    frames: Vec<f32>,
    actions: Vec<f32>,
    /// The same frames as RGB bytes, for the page.
    rgb: Vec<u8>,
    /// `(min, max)` of the speed and of the steering the model was trained on.
    ranges: [(f32, f32); 2],
    threads: usize,
}

fn main() -> ExitCode {
    common::exit(run(&Args::parse()))
}

fn run(args: &Args) -> Result<(), String> {
    let seed = Arc::new(load_seed(args)?);
    let listener =
        TcpListener::bind((args.host.as_str(), args.port)).map_err(|e| format!("{}:{}: {e}", args.host, args.port))?;
    let at = listener.local_addr().map_err(|e| e.to_string())?;
    println!("serving http://{at}/ (Ctrl-C stops)");
    for stream in listener.incoming() {
        let Ok(stream) = stream else { continue };
        let seed = Arc::clone(&seed);
        std::thread::spawn(move || {
            if let Err(e) = serve(stream, &seed) {
                eprintln!("connection ended: {e}");
            }
        });
    }
    Ok(())
}

fn load_seed(args: &Args) -> Result<Seed, String> {
    let model =
        Model::load(&args.source.weights).map_err(|e| format!("{}: {}", args.source.weights.display(), report(&e)))?;
    let c = *model.config();
    let episodes = Episodes::load(&args.source.episodes)
        .map_err(|e| format!("{}: {}", args.source.episodes.display(), report(&e)))?;
    let episode = episodes
        .episode(args.source.episode)
        .map_err(|e| format!("{}: {}", args.source.episodes.display(), report(&e)))?;
    if (episode.height, episode.width) != (c.height, c.width) || c.action_dim != Episodes::ACTION_DIM {
        return Err(format!(
            "{}: frames or actions do not fit the model",
            args.source.episodes.display()
        ));
    }
    if episode.len() < SEEDS {
        return Err(format!("episode {} has fewer than {SEEDS} frames", args.source.episode));
    }
    let mut frames = vec![0.0; SEEDS * c.frame_len()];
    for (i, frame) in frames.chunks_exact_mut(c.frame_len()).enumerate() {
        episode.frame_f32(i, frame).map_err(|e| report(&e))?;
    }
    let mut rgb = vec![0; frames.len()];
    frames_to_rgb(&frames, PixelLayout::Hwc, &c, &mut rgb).map_err(|e| report(&e))?;
    // Without ranges in the file, CarRacing's: speeds the recorder drove, steering [-1, 1].
    let ranges = match model.actions() {
        Some(specs) if specs.len() == 2 => [(specs[0].min, specs[0].max), (specs[1].min, specs[1].max)],
        _ => [(0.0, 60.0), (-1.0, 1.0)],
    };
    Ok(Seed {
        frames,
        actions: episode.actions[..(SEEDS - 1) * 2].to_vec(),
        rgb,
        ranges,
        threads: args.threads as usize,
        model: Arc::new(model),
    })
}

/// One connection: the page over plain HTTP, or a drive over the WebSocket.
fn serve(mut stream: TcpStream, seed: &Seed) -> Result<(), String> {
    stream
        .set_read_timeout(Some(Duration::from_secs(10)))
        .map_err(|e| e.to_string())?;
    let head = request_head(&stream)?;
    let first = head.lines().next().unwrap_or("");
    let upgrade = head.to_ascii_lowercase().contains("upgrade: websocket");
    let reply = |status: &str, kind: &str, body: &str| {
        format!(
            "HTTP/1.1 {status}\r\nContent-Type: {kind}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
            body.len()
        )
    };
    let answer = match first.split_whitespace().collect::<Vec<_>>()[..] {
        ["GET", "/ws", _] if upgrade => {
            let ws = tungstenite::accept(stream).map_err(|e| format!("handshake: {e}"))?;
            return drive(ws, seed);
        }
        ["GET", "/" | "/index.html", _] => reply("200 OK", "text/html; charset=utf-8", PAGE),
        ["GET", ..] => reply("404 Not Found", "text/plain", "not found\n"),
        _ => reply("400 Bad Request", "text/plain", "bad request\n"),
    };
    stream.write_all(answer.as_bytes()).map_err(|e| e.to_string())
}

/// The request's head (up to the blank line), peeked: the WebSocket handshake reads it again.
fn request_head(stream: &TcpStream) -> Result<String, String> {
    let mut buf = [0u8; 8192];
    let start = Instant::now();
    loop {
        let n = stream.peek(&mut buf).map_err(|e| e.to_string())?;
        let text = String::from_utf8_lossy(&buf[..n]);
        if let Some(end) = text.find("\r\n\r\n") {
            return Ok(text[..end].to_string());
        }
        if n == buf.len() || start.elapsed() > Duration::from_secs(10) {
            return Err("no request head".into());
        }
        if n == 0 {
            return Err("closed before a request".into());
        }
        std::thread::sleep(Duration::from_millis(2));
    }
}

/// What the page asks for, from its text messages.
struct Controls {
    /// The arrows held: -1, 0 or 1 each.
    steer: f32,
    throttle: f32,
    reset: bool,
    toggle_sampling: bool,
}

/// The drive: a simulator of its own, stepped and sent at up to [`TARGET_FPS`].
fn drive(mut ws: WebSocket<TcpStream>, seed: &Seed) -> Result<(), String> {
    let model = Arc::clone(&seed.model);
    let c = *model.config();
    let mut env = Environment::new(model, 1, 1)
        .and_then(|env| env.with_threads(seed.threads))
        .map_err(|e| report(&e))?;
    let samples = seed.model.samples();
    let [(speed_min, speed_max), (steer_min, steer_max)] = seed.ranges;
    let hello = format!(
        "{{\"speed\": [{speed_min}, {speed_max}], \"steering\": [{steer_min}, {steer_max}], \"samples\": {samples}, \"frame_hz\": {TARGET_FPS}}}"
    );
    ws.send(Message::text(hello)).map_err(|e| e.to_string())?;
    // A short read timeout: each tick takes what the page sent, then steps.
    ws.get_mut()
        .set_read_timeout(Some(Duration::from_millis(1)))
        .map_err(|e| e.to_string())?;
    ws.get_mut()
        .set_write_timeout(Some(Duration::from_secs(5)))
        .map_err(|e| e.to_string())?;
    let (mut frame, mut rgb) = (vec![0.0; c.frame_len()], vec![0u8; c.frame_len()]);
    let mut controls = Controls {
        steer: 0.0,
        throttle: 0.0,
        reset: true,
        toggle_sampling: false,
    };
    let (mut speed, mut steering, mut sampling) = (0.0f32, 0.0f32, false);
    let tick = Duration::from_secs_f64(1.0 / TARGET_FPS);
    loop {
        let start = Instant::now();
        read_controls(&mut ws, &mut controls)?;
        if std::mem::take(&mut controls.toggle_sampling) && samples {
            sampling = !sampling;
            env.set_sampling(if sampling { 1.0 } else { 0.0 }, 0)
                .map_err(|e| report(&e))?;
        }
        if std::mem::take(&mut controls.reset) {
            env.reset_from_frames(&seed.frames, &seed.actions)
                .map_err(|e| report(&e))?;
            (speed, steering) = (seed.actions[seed.actions.len() - 2], 0.0);
            for (i, rgb) in seed.rgb.chunks_exact(c.frame_len()).enumerate() {
                send_frame(&mut ws, 0, i as u8, (speed, steering, sampling), rgb)?;
            }
        }
        // Toward the held arrow's side, or back to straight when none is held.
        let target = if controls.steer < 0.0 {
            steer_min
        } else if controls.steer > 0.0 {
            steer_max
        } else {
            0.0
        };
        steering += (target - steering).clamp(-STEER_RATE, STEER_RATE);
        speed = (speed + controls.throttle * SPEED_RATE).clamp(speed_min, speed_max);
        env.step(&[speed, steering]).map_err(|e| report(&e))?;
        env.frames(&mut frame).map_err(|e| report(&e))?;
        frames_to_rgb(&frame, PixelLayout::Hwc, &c, &mut rgb).map_err(|e| report(&e))?;
        send_frame(&mut ws, 1, 0, (speed, steering, sampling), &rgb)?;
        if let Some(rest) = tick.checked_sub(start.elapsed()) {
            std::thread::sleep(rest);
        }
    }
}

/// Takes every message the page sent since the last tick; a malformed one is an error.
fn read_controls(ws: &mut WebSocket<TcpStream>, controls: &mut Controls) -> Result<(), String> {
    loop {
        let message = match ws.read() {
            Ok(message) => message,
            Err(tungstenite::Error::Io(e)) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {
                return Ok(())
            }
            Err(e) => return Err(e.to_string()),
        };
        let text = match message {
            Message::Text(text) => text,
            Message::Ping(_) | Message::Pong(_) => continue,
            Message::Close(_) => return Err("closed by the page".into()),
            _ => return Err("unexpected message".into()),
        };
        match text.split_whitespace().collect::<Vec<_>>()[..] {
            ["keys", steer, throttle] => {
                let key = |s: &str| match s {
                    "-1" => Some(-1.0),
                    "0" => Some(0.0),
                    "1" => Some(1.0),
                    _ => None,
                };
                let (Some(steer), Some(throttle)) = (key(steer), key(throttle)) else {
                    return Err(format!("malformed message {:?}", text.as_str()));
                };
                (controls.steer, controls.throttle) = (steer, throttle);
            }
            ["reset"] => controls.reset = true,
            ["sample"] => controls.toggle_sampling = true,
            _ => return Err(format!("malformed message {:?}", text.as_str())),
        }
    }
}

/// One frame to the page: kind (0 seed, 1 dream), index, speed, steering, sampling, RGB.
fn send_frame(
    ws: &mut WebSocket<TcpStream>,
    kind: u8,
    index: u8,
    (speed, steering, sampling): (f32, f32, bool),
    rgb: &[u8],
) -> Result<(), String> {
    let mut bytes = Vec::with_capacity(11 + rgb.len());
    bytes.extend_from_slice(&[kind, index]);
    bytes.extend_from_slice(&speed.to_le_bytes());
    bytes.extend_from_slice(&steering.to_le_bytes());
    bytes.push(sampling as u8);
    bytes.extend_from_slice(rgb);
    ws.send(Message::binary(bytes)).map_err(|e| e.to_string())
}
