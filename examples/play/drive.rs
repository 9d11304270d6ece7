//! One person's drive: a simulator of its own, stepped at up to [`TARGET_FPS`] from the arrows the
//! page holds, each frame sent as it is generated.

use crate::common::report;
use crate::http::short;
use crate::Seed;
use drivesim::{frames_to_rgb, Environment, PixelLayout};
use std::io::ErrorKind;
use std::net::TcpStream;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tungstenite::protocol::frame::coding::CloseCode;
use tungstenite::protocol::CloseFrame;
use tungstenite::{Message, WebSocket};

/// Frames per second the server aims at (it never sends faster).
pub const TARGET_FPS: f64 = 25.0;
/// How far the steering moves toward a held arrow's side (or back to straight) per frame.
const STEER_RATE: f32 = 0.08;
/// How far the speed moves per frame while up or down is held, in the speed's units.
const SPEED_RATE: f32 = 0.5;

/// What the page asks for, from its text messages.
#[derive(Debug, PartialEq)]
pub enum Command {
    /// The arrows held: steer and throttle, -1, 0 or 1 each.
    Keys(f32, f32),
    Reset,
    /// Sampling on or off.
    Sample,
}

/// One message of the page's protocol (`keys STEER THROTTLE`, `reset`, `sample`), read word by
/// word without collecting; anything else is `None`.
pub fn parse(text: &str) -> Option<Command> {
    let key = |word: &str| match word {
        "-1" => Some(-1.0),
        "0" => Some(0.0),
        "1" => Some(1.0),
        _ => None,
    };
    let mut words = text.split_ascii_whitespace();
    let command = match (words.next()?, words.next(), words.next()) {
        ("keys", Some(steer), Some(throttle)) => Command::Keys(key(steer)?, key(throttle)?),
        ("reset", None, None) => Command::Reset,
        ("sample", None, None) => Command::Sample,
        _ => return None,
    };
    words.next().is_none().then_some(command)
}

/// What the page asked for since the last tick.
struct Controls {
    steer: f32,
    throttle: f32,
    reset: bool,
    /// `sample` presses: each one toggles.
    toggles: u32,
}

/// How a tick's reading ended.
enum Read {
    /// Every message that had arrived was taken.
    Drained,
    /// The page closed the drive (its close answered).
    Closed,
}

/// The drive until the page leaves: `Ok` when it closes properly, the reason otherwise.
pub fn drive(mut ws: WebSocket<TcpStream>, seed: &Seed) -> Result<(), String> {
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
        toggles: 0,
    };
    let (mut speed, mut steering, mut sampling) = (0.0f32, 0.0f32, false);
    let tick = Duration::from_secs_f64(1.0 / TARGET_FPS);
    loop {
        let start = Instant::now();
        if let Read::Closed = read_controls(&mut ws, &mut controls)? {
            return Ok(());
        }
        if std::mem::take(&mut controls.toggles) % 2 == 1 && samples {
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

/// Takes every message the page sent since the last tick; a malformed one is an error, logged
/// short (a message is at most [`crate::http::MAX_MESSAGE`] bytes; the library refuses longer).
fn read_controls(ws: &mut WebSocket<TcpStream>, controls: &mut Controls) -> Result<Read, String> {
    loop {
        let message = match ws.read() {
            Ok(message) => message,
            Err(tungstenite::Error::Io(e)) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {
                return Ok(Read::Drained)
            }
            Err(tungstenite::Error::ConnectionClosed) => return Ok(Read::Closed),
            Err(e) => return Err(e.to_string()),
        };
        let text = match message {
            Message::Text(text) => text,
            Message::Ping(_) | Message::Pong(_) => continue,
            Message::Close(_) => {
                // The answer to the page's close is queued by the read: send it.
                let _ = ws.flush();
                return Ok(Read::Closed);
            }
            Message::Binary(bytes) => return Err(format!("a binary message ({} bytes)", bytes.len())),
            Message::Frame(_) => return Err("a raw frame".into()),
        };
        match parse(&text) {
            Some(Command::Keys(steer, throttle)) => (controls.steer, controls.throttle) = (steer, throttle),
            Some(Command::Reset) => controls.reset = true,
            Some(Command::Sample) => controls.toggles += 1,
            None => return Err(format!("malformed message {}", short(&text))),
        }
    }
}

/// Tells a page that came while every drive was taken, with a close it can show, and waits
/// (briefly) for its answer.
pub fn refuse(mut ws: WebSocket<TcpStream>, drives: usize) {
    let reason = format!("the server is busy: {drives} drives at once; try again later");
    let close = CloseFrame {
        code: CloseCode::Again,
        reason: reason.into(),
    };
    let _ = ws.get_mut().set_read_timeout(Some(Duration::from_secs(1)));
    if ws.close(Some(close)).and_then(|()| ws.flush()).is_ok() {
        // Until the page's close arrives (or a second passes): then the socket is dropped.
        for _ in 0..8 {
            if ws.read().is_err() {
                break;
            }
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

#[cfg(test)]
mod tests {
    use super::{parse, Command};

    #[test]
    fn the_protocol_and_nothing_else() {
        assert_eq!(parse("keys -1 1"), Some(Command::Keys(-1.0, 1.0)));
        assert_eq!(parse(" keys 0  0 "), Some(Command::Keys(0.0, 0.0)));
        assert_eq!(parse("reset"), Some(Command::Reset));
        assert_eq!(parse("sample"), Some(Command::Sample));
        for bad in [
            "",
            "keys",
            "keys 1",
            "keys 2 0",
            "keys 1 0 0",
            "reset now",
            "steer left please",
            "keys NaN 0",
        ] {
            assert_eq!(parse(bad), None, "{bad:?}");
        }
    }
}
