//! Drive the dream yourself: serves a page where the arrow keys steer a car inside the learned
//! simulator, frames pushed to the browser as they are generated.
//!
//! ```text
//! cargo run --release --example play                      # then open http://127.0.0.1:8080/
//! cargo run --release --example play -- --port 8000 --episodes rec.safetensors --episode 3 --threads 2
//! ```
//!
//! The server is std's `TcpListener` with a thread per connection and `tungstenite` for the
//! WebSocket: a blocking, dependency-light server (no async runtime) is enough for a page that a
//! few people drive, and each drive owns its simulator, dropped with the connection. `GET /`
//! answers the page (`page.html`, built in); `GET /ws` upgrades to the WebSocket. The page sends
//! text messages: `keys STEER THROTTLE` (each -1, 0 or 1: the arrow keys held), `reset`,
//! `sample`. The server sends one text message first (the model's action ranges and whether it
//! samples), then binary frames: a kind byte (0 a seed frame, 1 the dream), the speed and
//! steering (f32, little-endian), a sampling byte, then the frame's RGB bytes. Anything else from
//! the page ends that connection only.
//!
//! Bounded against hostile clients: at most `--max-drives` drives (each steps a simulator at 25
//! frames a second; a page beyond them gets a WebSocket close 1013 with the reason, and the
//! drives already running keep their frame rate) and `--max-pending` connections still sending
//! their request (more are answered 503 at once); a request head within 8 KiB (431 beyond) and
//! 10 s, read by blocking reads; WebSocket messages within 256 bytes; a bad message logged as
//! one short line. `tests/browser/abuse.py` holds the server to this.

#[path = "../common.rs"]
mod common;
mod drive;
mod http;

use clap::Parser;
use common::{report, SeedArgs};
use drivesim::{frames_to_rgb, Episodes, Model, PixelLayout};
use http::HeadError;
use std::io::Write;
use std::net::{TcpListener, TcpStream};
use std::process::ExitCode;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// The page, served at `/`.
const PAGE: &str = include_str!("page.html");
/// Seed frames a reset encodes.
const SEEDS: usize = 5;
/// How long a connection may take to send its request head.
const HEAD_DEADLINE: Duration = Duration::from_secs(10);

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
    /// Drives at once (default: two per core; each takes about a quarter of a core at 25 fps)
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=1024))]
    max_drives: Option<u32>,
    /// Connections still sending their request at once (more are answered 503 at once)
    #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u32).range(1..=65536))]
    max_pending: u32,
}

/// What every connection starts from.
pub struct Seed {
    pub model: Arc<Model>,
    /// `SEEDS` frames in [-1, 1] and the `SEEDS - 1` actions between them.
    pub frames: Vec<f32>,
    pub actions: Vec<f32>,
    /// The same frames as RGB bytes, for the page.
    pub rgb: Vec<u8>,
    /// `(min, max)` of the speed and of the steering the model was trained on.
    pub ranges: [(f32, f32); 2],
    pub threads: usize,
}

fn main() -> ExitCode {
    common::exit(run(&Args::parse()))
}

fn run(args: &Args) -> Result<(), String> {
    let seed = Arc::new(load_seed(args)?);
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let drives = Slots::new(args.max_drives.map_or(2 * cores, |n| n as usize));
    let pending = Slots::new(args.max_pending as usize);
    let listener =
        TcpListener::bind((args.host.as_str(), args.port)).map_err(|e| format!("{}:{}: {e}", args.host, args.port))?;
    let at = listener.local_addr().map_err(|e| e.to_string())?;
    println!(
        "serving http://{at}/ (at most {} drives at once; Ctrl-C stops)",
        drives.max
    );
    for stream in listener.incoming() {
        let Ok(mut stream) = stream else { continue };
        let Some(waiting) = pending.take() else {
            // Refused before anything is read, from this thread: no thread per flood connection.
            let _ = stream.set_write_timeout(Some(Duration::from_millis(100)));
            let body = "too many connections at once; try again later\n";
            let _ = write!(
                stream,
                "HTTP/1.1 503 Service Unavailable\r\nContent-Type: text/plain\r\nContent-Length: {}\r\nConnection: close\r\nRetry-After: 1\r\n\r\n{body}",
                body.len()
            );
            continue;
        };
        let (seed, drives) = (Arc::clone(&seed), Arc::clone(&drives));
        let spawned = std::thread::Builder::new().spawn(move || {
            if let Err(e) = serve(stream, &seed, &drives, waiting) {
                eprintln!("connection ended: {e}");
            }
        });
        if let Err(e) = spawned {
            // The system would not start a thread: this connection is dropped, the server goes on.
            eprintln!("connection dropped: no thread for it ({e})");
        }
    }
    Ok(())
}

/// One connection: the page over plain HTTP, or a drive over the WebSocket. `waiting` holds its
/// place among the pending connections until the request is read.
fn serve(mut stream: TcpStream, seed: &Seed, drives: &Arc<Slots>, waiting: Slot) -> Result<(), String> {
    let request = match http::read_request(&mut stream, HEAD_DEADLINE) {
        Ok(request) => request,
        Err(HeadError::TooLarge) => {
            return http::reply(
                stream,
                "431 Request Header Fields Too Large",
                "text/plain",
                "request head over 8 KiB\n",
            )
        }
        Err(HeadError::Malformed(why)) => {
            return http::reply(stream, "400 Bad Request", "text/plain", &format!("{why}\n"))
        }
        Err(HeadError::Gone(why)) => return Err(why),
    };
    drop(waiting);
    match (request.method.as_str(), request.path.as_str()) {
        ("GET", "/ws") if http::is_upgrade(&request) => {
            let taken = drives.take();
            let ws = http::upgrade(stream, request)?;
            match taken {
                Some(_drive) => drive::drive(ws, seed),
                None => {
                    drive::refuse(ws, drives.max);
                    Err(format!("refused a drive: {} at once", drives.max))
                }
            }
        }
        ("GET", "/ws") => http::reply(stream, "400 Bad Request", "text/plain", "not a WebSocket upgrade\n"),
        ("GET", "/" | "/index.html") => http::reply(stream, "200 OK", "text/html; charset=utf-8", PAGE),
        ("GET", _) => http::reply(stream, "404 Not Found", "text/plain", "not found\n"),
        _ => http::reply(stream, "405 Method Not Allowed", "text/plain", "only GET\n"),
    }
}

/// A bounded count of things at once (drives, pending connections).
struct Slots {
    used: AtomicUsize,
    max: usize,
}

/// One taken place of [`Slots`], given back when dropped.
struct Slot(Arc<Slots>);

impl Slots {
    fn new(max: usize) -> Arc<Self> {
        Arc::new(Slots {
            used: AtomicUsize::new(0),
            max,
        })
    }

    fn take(self: &Arc<Self>) -> Option<Slot> {
        self.used
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| (n < self.max).then_some(n + 1))
            .ok()
            .map(|_| Slot(Arc::clone(self)))
    }
}

impl Drop for Slot {
    fn drop(&mut self) {
        self.0.used.fetch_sub(1, Ordering::AcqRel);
    }
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
